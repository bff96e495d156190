"""What the 3-D viewer shows, computed without the viewer: finding and loading saved maps,
validating them, colouring voxels (and the mesh of a map with a geometry layer) in each colour
mode, the legend, filtering by class and height, and choosing cubes or points. A map's mesh can
be left for later at load (`load_view_map(..., mesh=False)`) and made by `prepare_mesh`, which
says what it is doing; `coarse_voxels` is the map's cheap preview meanwhile. Nothing here
imports viser.

Shape legend: N voxels, K classes, T frames, P mesh vertices, F mesh faces.
"""

import dataclasses
import html
import os
import zipfile
import zlib
from typing import Callable, Iterable, NamedTuple, Optional, Sequence

import numpy as np

INSTALL_HINT = ("the viewer needs viser: pip install 'jaxfusion[viewer]' "
                "(or pip install 'viser>=1.1,<2')")

# Colour modes: key → title shown in the viewer.
COLOR_MODES = {
    "class": "class",
    "entropy": "entropy",
    "confidence": "Dirichlet confidence ᾱ",
    "hits": "hit count",
    "correct": "right / wrong vs GT",
}
RIGHT_COLOR = (40, 170, 70)
WRONG_COLOR = (220, 40, 40)
UNSCORED_COLOR = (175, 175, 175)   # a voxel the GT map does not have (or ignores)
NO_VOXEL_COLOR = (160, 160, 160)   # a mesh vertex without a semantic voxel (jaxfusion.io's grey)
# Colour modes of the mesh (hit counts are per voxel, not on the surface). "confidence" on the
# mesh is the posterior's max at the vertex (every rule has one), not ᾱ.
MESH_COLOR_MODES = ("class", "entropy", "confidence", "correct")
MESH_CONFIDENCE_TITLE = "confidence (max posterior)"
# What the viewer shows of a map that has a mesh (a map without one always shows its voxels).
SHOW_CHOICES = ("mesh", "voxels", "mesh + voxels")
DEFAULT_MAX_CUBES = 200_000
COLORMAP = "viridis"
# While a mesh is being prepared its map is shown as at most this many coarse voxels, drawn as
# cubes (`coarse_voxels`): light enough for a software-rendered page (all 153 k voxels of
# bench/viewer_open.py's corridor as cubes took it 15 s to draw and slowed the meshing beside
# it almost 3×).
DEFAULT_PREVIEW_VOXELS = 20_000


class MeshSource(NamedTuple):
  """What the mesh of a map loaded with `mesh=False` is made from (by `prepare_mesh`).

  Attributes:
    state: the loaded MapState (its geometry layer gives the surface, its semantic layer the
      vertices' labels).
    gt: the GT voxel labels saved beside the map (`load_gt`), or None.
  """
  state: object
  gt: Optional[dict] = None


@dataclasses.dataclass(frozen=True, eq=False)
class ViewMap:
  """One saved map, read out for display.

  Attributes:
    path: the `.npz` file.
    name: what the viewer calls it: the rule's paper name, β and aggregation ("D+R β=0.3"),
      and "+ free space" for a map with free-space clearing (its cleared voxels, which
      `read_map` leaves out, are not shown).
    sequence: the sequence it was fused from (maps of one sequence share a view).
    class_names: the K class names (or "0" … "K-1" when the map has none).
    voxel_size: voxel edge in metres.
    centers: `(N, 3) float32` voxel centres in metres.
    labels: `(N,) int32` predicted class.
    hits: `(N,) int32` pixels fused into each voxel.
    entropy: `(N,) float32` posterior entropy in nats.
    confidence: `(N,) float32` Dirichlet confidence ᾱ of the predicted class, or None for
      rules without one.
    gt_labels: `(N,) int32` GT label of each voxel (−1 where the GT map has none), or None
      when no GT map is saved beside the map.
    poses: `(T, 4, 4) float32` camera-to-world poses of the fused frames, or None.
    camera: intrinsics of those frames (`fx, fy, cx, cy, height, width`), or None.
    mesh: the surface of the map's geometry layer (`jaxfusion.mesh.Mesh`, extracted once at
      load, each vertex labelled from the semantic layer), or None for a map without a
      geometry layer (or one whose mesh has no face).
    mesh_gt_labels: `(P,) int32` GT label of the (semantic-size) voxel each mesh vertex lies
      in (−1 where the GT has no voxel there or the vertex has no label), or None without a
      mesh or a GT map.
    mesh_source: for a map loaded with `mesh=False` whose geometry layer is not meshed yet,
      what `prepare_mesh` makes the mesh from (`mesh` is None until then); else None.
  """
  path: str
  name: str
  sequence: str
  class_names: tuple
  voxel_size: float
  centers: np.ndarray
  labels: np.ndarray
  hits: np.ndarray
  entropy: np.ndarray
  confidence: Optional[np.ndarray] = None
  gt_labels: Optional[np.ndarray] = None
  poses: Optional[np.ndarray] = None
  camera: Optional[dict] = None
  mesh: Optional[object] = None
  mesh_gt_labels: Optional[np.ndarray] = None
  mesh_source: Optional[MeshSource] = None

  @property
  def mesh_pending(self) -> bool:
    """True while the map's geometry layer is loaded but not meshed yet (`prepare_mesh`)."""
    return self.mesh_source is not None

  def __len__(self) -> int:
    return int(len(self.labels))

  @property
  def num_classes(self) -> int:
    return len(self.class_names)


def is_map_file(path: str) -> bool:
  """True if `path` is a `.npz` written by `jaxfusion.io.save_map` (reads only its index)."""
  return _not_a_map(path) is None


def _not_a_map(path: str):
  """None for a map file (judged by its index), else why it is not one, in a few words."""
  if not os.path.isfile(path):
    return "not a file"
  try:
    with np.load(path) as data:
      names = data.files
  except (OSError, ValueError, TypeError, AttributeError, EOFError, zipfile.BadZipFile,
          zlib.error) as e:   # not .npz / a .npy / damaged
    return f"{type(e).__name__}: {e}" if isinstance(e, (zipfile.BadZipFile, EOFError)) else (
        "not an .npz archive")
  if "metadata" in names and "keys" in names:
    return None
  return "no map arrays in it"


def find_map_files(paths: Sequence[str]) -> list:
  """The map files named by `paths`: files, or folders searched recursively for map `.npz`s.

  Other `.npz` files in a folder (GT voxel labels, the front-end cache) are skipped; a file
  named directly must be a map.

  Raises:
    FileNotFoundError: a path does not exist.
    ValueError: no paths, a named file that is not a map, or a folder without maps.
  """
  if isinstance(paths, (str, os.PathLike)):
    paths = [paths]
  if not paths:
    raise ValueError("give at least one map file or folder")
  found = []
  for path in map(str, paths):
    if not os.path.exists(path):
      raise FileNotFoundError(f"no such file or folder: {path}")
    if os.path.isdir(path):
      inside = []
      for root, dirs, files in os.walk(path):
        dirs[:] = sorted(d for d in dirs if not d.startswith("."))
        inside += [os.path.join(root, f) for f in sorted(files)
                   if f.endswith(".npz") and not f.startswith(".")
                   and is_map_file(os.path.join(root, f))]
      if not inside:
        raise ValueError(f"{path}: no jaxfusion map (.npz from `jaxfusion run` or `demo`) in "
                         "this folder")
      found += inside
    elif (problem := _not_a_map(path)) is None:
      found.append(path)
    else:
      raise ValueError(f"{path} is not a jaxfusion map file (a .npz written by `jaxfusion run` "
                       f"or `demo`; {problem})")
  unique, seen = [], set()
  for path in found:
    real = os.path.realpath(path)
    if real not in seen:
      seen.add(real)
      unique.append(path)
  return unique


def gt_path_for(path: str, sequence: Optional[str]) -> Optional[str]:
  """The GT voxel labels saved beside a map, if any.

  `jaxfusion run` writes `<stem>_gt.npz` next to `<stem>.npz`; the demo writes one
  `<sequence>_gt.npz` per sequence in its `maps/` folder.
  """
  stem = os.path.splitext(path)[0]
  candidates = [stem + "_gt.npz"]
  if sequence:
    candidates.append(os.path.join(os.path.dirname(path), f"{sequence}_gt.npz"))
  return next((c for c in candidates if os.path.isfile(c)), None)


def load_gt(path: str) -> dict:
  """GT voxel labels (`coords (M, 3) int32`, `labels (M,) int32`) as written by run/demo."""
  from jaxfusion import io  # pylint: disable=import-outside-toplevel
  what = "GT voxel-label file with 'coords' and 'labels'"
  f = io.read_npz(path, what=what, required=("coords", "labels"))
  coords, labels = f["coords"], f["labels"]
  if coords.ndim != 2 or coords.shape[1] != 3 or labels.shape != (len(coords),):
    raise ValueError(f"{path}: GT coords must be (M, 3) and labels (M,); got {coords.shape} "
                     f"and {labels.shape}")
  if not (np.issubdtype(coords.dtype, np.integer) and np.issubdtype(labels.dtype, np.integer)):
    raise ValueError(f"{path}: GT coords and labels must be integers; got {coords.dtype} and "
                     f"{labels.dtype}")
  return {"coords": coords.astype(np.int32), "labels": labels.astype(np.int32)}


def gt_labels_for(coords: np.ndarray, gt: dict) -> np.ndarray:
  """`(N,) int32` GT label of each map voxel (−1 where the GT has no voxel there)."""
  from jaxfusion import metrics
  out = np.full(len(coords), -1, np.int32)
  if len(coords) and len(gt["coords"]):
    map_index, gt_index = metrics.match_voxels(np.asarray(coords, np.int32), gt["coords"])
    out[map_index] = gt["labels"][gt_index]
  return out


def vertex_gt_labels(vertices: np.ndarray, voxel_size, coords: np.ndarray,
                     gt_labels: np.ndarray) -> np.ndarray:
  """`(P,) int32` label of the voxel each point of `vertices (P, 3)` lies in (−1 where none).

  A point lies in the voxel `floor(p / voxel_size)`, computed by the engine's own
  `camera.voxel_keys` (the arithmetic `jf.query` — and so the mesh's vertex labels — uses);
  that voxel is looked up among the voxels `coords (M, 3) int` (unique) labelled
  `gt_labels (M,)` — e.g. a GT voxel-label file's.
  """
  import jax.numpy as jnp
  from jaxfusion import camera, metrics
  out = np.full(len(vertices), -1, np.int32)
  if not len(vertices) or not len(coords):
    return out
  keys, in_range = camera.voxel_keys(jnp.asarray(vertices, jnp.float32), voxel_size)
  keys, in_range = np.asarray(keys), np.asarray(in_range)
  unique, inverse = np.unique(keys, axis=0, return_inverse=True)
  map_index, unique_index = metrics.match_voxels(np.asarray(coords, np.int32), unique)
  label_of_unique = np.full(len(unique), -1, np.int32)
  label_of_unique[unique_index] = np.asarray(gt_labels, np.int32)[map_index]
  out[:] = label_of_unique[inverse.reshape(-1)]
  out[~in_range] = -1
  return out


def map_name(rule) -> str:
  """The dropdown name of a map: the rule's paper name, β when it has one, mean aggregation."""
  from jaxfusion import rules
  name = rules.display_name(rule)
  if "beta" in rule.hparams:
    beta = np.asarray(rule.hparams["beta"], np.float64)
    name += f" β={float(beta):g}" if beta.ndim == 0 else f" β={np.round(beta, 3).tolist()}"
  if rule.aggregate != "sum":
    name += f" ({rule.aggregate})"
  return name


def load_view_map(path: str, *, mesh: bool = True) -> ViewMap:
  """Loads one map file (and the GT saved beside it) for display.

  Args:
    path: the map file.
    mesh: extract the mesh of a map with a geometry layer now (the largest part of loading a
      building-sized map); False leaves it to `prepare_mesh` (`mesh_source` holds what it
      needs).

  Raises:
    FileNotFoundError / ValueError: no file, or not a map file.
  """
  import jaxfusion as jf
  from jaxfusion import io
  state, rule, meta = io.load_map(path)
  voxels = jf.read_map(state)
  k = state.num_classes
  names = tuple(meta.get("class_names") or (str(i) for i in range(k)))
  labels = voxels["labels"]
  confidence = None
  if "confidence" in voxels:
    confidence = voxels["confidence"][np.arange(len(labels)), labels].astype(np.float32)
  extra = meta.get("extra") or {}
  sequence = extra.get("sequence") or os.path.splitext(os.path.basename(path))[0]
  gt_file = gt_path_for(path, extra.get("sequence"))
  gt = None if gt_file is None else load_gt(gt_file)
  gt_labels = None if gt is None else gt_labels_for(voxels["coords"], gt)
  trajectory = io.load_trajectory(path)
  view = ViewMap(
      path=path, name=map_name(rule) + (" + free space" if state.free_space is not None else ""),
      sequence=str(sequence), class_names=names,
      voxel_size=float(state.voxel_size), centers=voxels["centers"], labels=labels,
      hits=voxels["hits"], entropy=voxels["entropy"], confidence=confidence,
      gt_labels=gt_labels,
      poses=None if trajectory is None else trajectory["T_world_cam"],
      camera=None if trajectory is None else trajectory["camera"],
      mesh_source=None if state.geometry is None else MeshSource(state, gt))
  return prepare_mesh(view) if mesh else view


def prepare_mesh(m: ViewMap, *, progress: Optional[Callable[[str], None]] = None) -> ViewMap:
  """`m` with its mesh made from `m.mesh_source` (`m` itself when it has none pending): the
  geometry layer's surface, each vertex labelled from the semantic layer, as
  `jf.extract_mesh(state)` gives it, and the GT label of each vertex when a GT map is saved
  beside the map. `mesh` stays None when the surface has no face.

  Args:
    m: a map loaded with `load_view_map(..., mesh=False)`.
    progress: called with one line before each stage (marching cubes, labelling, GT), e.g.
      "marching cubes on 13546 blocks …".
  """
  from jaxfusion import mesh as mesh_lib  # pylint: disable=import-outside-toplevel
  if m.mesh_source is None:
    return m
  say = progress or (lambda _: None)
  state, gt = m.mesh_source
  say(f"marching cubes on {int(state.geometry.num_blocks)} blocks of the geometry layer …")
  vertices, faces = mesh_lib.marching_cubes(state.geometry)
  mesh = mesh_gt = None
  if len(faces):
    say(f"labelling {len(vertices)} vertices and {len(faces)} faces from the semantic "
        "layer …")
    mesh = mesh_lib.label_mesh(
        mesh_lib.Mesh(vertices=vertices, faces=faces,
                      normals=mesh_lib.vertex_normals(vertices, faces)), state)
    if gt is not None:
      say(f"GT labels of {len(vertices)} vertices …")
      # The GT where the vertex is, whichever voxel its label was read from (extract_mesh may
      # fill a vertex outside the map from a neighbouring voxel).
      mesh_gt = vertex_gt_labels(mesh.vertices, state.voxel_size, gt["coords"], gt["labels"])
      mesh_gt[mesh.labels < 0] = -1
  return dataclasses.replace(m, mesh=mesh, mesh_gt_labels=mesh_gt, mesh_source=None)


def check_same_classes(maps: Sequence[ViewMap]) -> None:
  """Raises ValueError (one line) unless all maps have the same class list."""
  first = maps[0]
  for m in maps[1:]:
    if m.class_names != first.class_names:
      raise ValueError(f"maps have different class lists: {first.path} has "
                       f"{list(first.class_names)}, {m.path} has {list(m.class_names)}")


def load_maps(paths: Sequence[str], *, mesh: bool = True,
              progress: Optional[Callable[[str], None]] = None) -> list:
  """Finds, loads and validates the maps named by `paths` (files or folders).

  Maps of one sequence with the same name (e.g. the same rule in two folders) get the file
  name added so that every map can be told apart.

  Args:
    paths: map files or folders holding them.
    mesh: extract the meshes now (False: leave them to `prepare_mesh`; see `load_view_map`).
    progress: called with one line before each file is loaded ("loading a.npz (1 of 3) …").

  Raises:
    FileNotFoundError / ValueError: see `find_map_files`; maps of different class lists.
  """
  files = find_map_files(paths)
  maps = []
  for i, path in enumerate(files):
    if progress is not None:
      progress(f"loading {path} ({i + 1} of {len(files)}) …")
    maps.append(load_view_map(path, mesh=mesh))
  check_same_classes(maps)
  counts = {}
  for m in maps:
    counts[(m.sequence, m.name)] = counts.get((m.sequence, m.name), 0) + 1
  return [dataclasses.replace(m, name=f"{m.name} [{os.path.basename(m.path)}]")
          if counts[(m.sequence, m.name)] > 1 else m for m in maps]


def by_sequence(maps: Iterable[ViewMap]) -> dict:
  """`{sequence: {map name: ViewMap}}`, in the order first seen."""
  out = {}
  for m in maps:
    out.setdefault(m.sequence, {})[m.name] = m
  return out


def class_palette(class_names: Sequence[str]) -> np.ndarray:
  """`(K, 3) uint8` class colours: the project's tables for its class lists, else tab20."""
  from jaxfusion.datasets import classes  # pylint: disable=import-outside-toplevel
  return classes.palette(class_names)


def color_modes(m: ViewMap) -> tuple:
  """The colour modes a map supports (confidence needs a Dirichlet rule, correct a GT map)."""
  return tuple(mode for mode in COLOR_MODES
               if (mode != "confidence" or m.confidence is not None)
               and (mode != "correct" or m.gt_labels is not None))


def scalar_field(m: ViewMap, mode: str) -> tuple:
  """The per-voxel value a continuous colour mode shows, and its colour scale.

  Entropy uses a fixed scale [0, log K] nats (comparable across maps); hits and ᾱ use a log
  scale from the map's smallest to largest value.

  Returns:
    `(t, lo, hi, unit)`: `t (N,) float32` position on the colour scale in [0, 1], the values
    at its ends, and their unit.
  """
  if mode == "entropy":
    hi = float(np.log(max(m.num_classes, 2)))
    return np.clip(m.entropy / hi, 0.0, 1.0).astype(np.float32), 0.0, hi, "nats"
  if mode in ("hits", "confidence"):
    values = m.hits if mode == "hits" else m.confidence
    if values is None:
      raise ValueError(f"{m.name}: this map has no Dirichlet confidence ᾱ (only the D and D+R "
                       "rules keep one)")
    v = np.maximum(np.asarray(values, np.float64), np.finfo(np.float32).tiny)
    if len(v) == 0:
      return np.zeros(0, np.float32), 0.0, 0.0, ""
    lo, hi = float(v.min()), float(v.max())
    span = np.log(hi) - np.log(lo)
    t = (np.log(v) - np.log(lo)) / span if span > 0 else np.zeros_like(v)
    return t.astype(np.float32), lo, hi, "pixels" if mode == "hits" else ""
  raise ValueError(f"{mode!r} is not a continuous colour mode")


def colormap(t: np.ndarray) -> np.ndarray:
  """`(N,) float` in [0, 1] → `(N, 3) uint8` colours of the viewer's colour scale."""
  import matplotlib
  lut = (np.asarray(matplotlib.colormaps[COLORMAP](np.linspace(0, 1, 256)))[:, :3] * 255)
  index = np.clip(np.round(np.asarray(t, np.float64) * 255), 0, 255).astype(np.int64)
  return np.round(lut).astype(np.uint8)[index]


def voxel_colors(m: ViewMap, mode: str, palette: np.ndarray) -> np.ndarray:
  """`(N, 3) uint8` colour of every voxel of `m` in colour mode `mode`.

  Args:
    m: the map.
    mode: one of `COLOR_MODES`.
    palette: `(K, 3) uint8` class colours (mode "class").

  Raises:
    ValueError: unknown mode, a mode the map does not support, a palette of the wrong size.
  """
  if mode not in COLOR_MODES:
    raise ValueError(f"colour mode must be one of {list(COLOR_MODES)}; got {mode!r}")
  if mode == "class":
    palette = np.asarray(palette, np.uint8)
    if palette.ndim != 2 or palette.shape[1] != 3 or len(palette) < m.num_classes:
      raise ValueError(f"palette must be (K ≥ {m.num_classes}, 3); got {palette.shape}")
    return palette[m.labels]
  if mode == "correct":
    if m.gt_labels is None:
      raise ValueError(f"{m.name}: no GT voxel labels are saved beside {m.path}")
    out = np.empty((len(m), 3), np.uint8)
    out[:] = UNSCORED_COLOR
    scored = m.gt_labels >= 0
    out[scored & (m.gt_labels == m.labels)] = RIGHT_COLOR
    out[scored & (m.gt_labels != m.labels)] = WRONG_COLOR
    return out
  return colormap(scalar_field(m, mode)[0])


def legend(m: ViewMap, mode: str, palette: np.ndarray) -> list:
  """`[(text, (r, g, b)), ...]` explaining the colours of `voxel_colors(m, mode, palette)`."""
  if mode == "class":
    counts = np.bincount(m.labels, minlength=m.num_classes)
    return [(f"{name} ({int(n)})", tuple(int(c) for c in palette[i]))
            for i, (name, n) in enumerate(zip(m.class_names, counts))]
  if mode == "correct":
    if m.gt_labels is None:
      raise ValueError(f"{m.name}: no GT voxel labels are saved beside {m.path}")
    scored = m.gt_labels >= 0
    right = int(np.sum(scored & (m.gt_labels == m.labels)))
    wrong = int(np.sum(scored)) - right
    acc = f", accuracy {100 * right / max(right + wrong, 1):.1f} %"
    return [(f"right ({right}{acc})", RIGHT_COLOR), (f"wrong ({wrong})", WRONG_COLOR),
            (f"not in GT ({len(m) - right - wrong})", UNSCORED_COLOR)]
  _, lo, hi, unit = scalar_field(m, mode)
  stops = np.linspace(0.0, 1.0, 5)
  if mode == "entropy":
    values = lo + stops * (hi - lo)
  else:
    values = np.exp(np.log(max(lo, 1e-38)) + stops * (np.log(max(hi, 1e-38)) -
                                                      np.log(max(lo, 1e-38))))
  colors = colormap(stops)
  return [(f"{v:.3g} {unit}".rstrip(), tuple(int(x) for x in c))
          for v, c in zip(values, colors)]


def legend_html(entries: Sequence[tuple]) -> str:
  """The legend as HTML: a colour swatch and the (escaped) text per entry; an entry whose
  colour is None is a heading."""
  rows = []
  for text, color in entries:
    if color is None:   # a heading
      rows.append('<div style="font-size:0.85em;font-weight:bold;margin-top:4px;">'
                  f'{html.escape(str(text))}</div>')
      continue
    r, g, b = color
    rows.append(
        '<div style="display:flex;align-items:center;gap:6px;font-size:0.85em;">'
        f'<span style="display:inline-block;width:0.9em;height:0.9em;border:1px solid #888;'
        f'background:rgb({int(r)},{int(g)},{int(b)});"></span>{html.escape(str(text))}</div>')
  return "".join(rows)


def visible_mask(m: ViewMap, *, hidden_classes: Iterable[int] = (),
                 max_height: Optional[float] = None, up_axis: int = 2) -> np.ndarray:
  """`(N,) bool`: voxels whose predicted class is not hidden and whose centre is at most
  `max_height` metres along the up axis (None: no height cut)."""
  hidden = np.asarray(sorted(set(int(c) for c in hidden_classes)), np.int64)
  if np.any((hidden < 0) | (hidden >= m.num_classes)):
    raise ValueError(f"hidden classes must be in [0, {m.num_classes}); got {hidden.tolist()}")
  if up_axis not in (0, 1, 2):
    raise ValueError(f"up_axis must be 0, 1 or 2; got {up_axis}")
  keep = ~np.isin(m.labels, hidden)
  if max_height is not None:
    keep &= m.centers[:, up_axis] <= max_height
  return keep


# The mesh ------------------------------------------------------------------------------------


def shown_layers(m: ViewMap, show: str) -> tuple:
  """`(mesh, voxels)`: which layers of `m` are drawn for the "Show" choice `show` (one of
  `SHOW_CHOICES`). A map without a mesh always shows its voxels, whatever `show` says; a map
  whose mesh is being prepared (`mesh_pending`) shows what `show` says, the mesh once it is
  there."""
  if show not in SHOW_CHOICES:
    raise ValueError(f"show must be one of {list(SHOW_CHOICES)}; got {show!r}")
  if m.mesh is None and not m.mesh_pending:
    return False, True
  return show != "voxels", show != "mesh"


def mesh_color_modes(m: ViewMap) -> tuple:
  """The colour modes the mesh of `m` supports (none without a mesh; correct needs GT, which a
  mesh still being prepared will have when a GT map is saved beside the map)."""
  if m.mesh is None:
    if not m.mesh_pending:
      return ()
    return tuple(mode for mode in MESH_COLOR_MODES
                 if mode != "correct" or m.mesh_source.gt is not None)
  return tuple(mode for mode in MESH_COLOR_MODES
               if mode != "correct" or m.mesh_gt_labels is not None)


def shown_color_modes(m: ViewMap, show: str) -> tuple:
  """The colour modes that every layer drawn for `show` supports, in `COLOR_MODES` order."""
  mesh, voxels = shown_layers(m, show)
  modes = set(COLOR_MODES)
  if voxels:
    modes &= set(color_modes(m))
  if mesh:
    modes &= set(mesh_color_modes(m))
  return tuple(mode for mode in COLOR_MODES if mode in modes)


def mode_titles(m: ViewMap, show: str) -> dict:
  """`{mode: title}` of the colour control for `show`: confidence is the posterior's max on
  the mesh and ᾱ on the voxels, and its title says which."""
  mesh, voxels = shown_layers(m, show)
  titles = {mode: COLOR_MODES[mode] for mode in shown_color_modes(m, show)}
  if "confidence" in titles and mesh:
    titles["confidence"] = (MESH_CONFIDENCE_TITLE if not voxels else
                            "confidence (mesh: max posterior, voxels: ᾱ)")
  return titles


def _check_mesh_mode(m: ViewMap, mode: str) -> None:
  if m.mesh is None:
    raise ValueError(f"{m.name}: this map has no mesh (it was saved without a geometry layer)")
  if mode not in MESH_COLOR_MODES:
    raise ValueError(f"mesh colour mode must be one of {list(MESH_COLOR_MODES)}; got {mode!r}")
  if mode == "correct" and m.mesh_gt_labels is None:
    raise ValueError(f"{m.name}: no GT voxel labels are saved beside {m.path}")


def mesh_scalar(m: ViewMap, mode: str) -> tuple:
  """The per-vertex value a continuous mode shows on the mesh, on a fixed scale: entropy over
  [0, log K] nats (as the voxels), confidence (the posterior's max) over [1/K, 1].

  Returns:
    `(t, lo, hi, unit)` as `scalar_field`.
  """
  _check_mesh_mode(m, mode)
  k = max(m.num_classes, 2)
  if mode == "entropy":
    hi = float(np.log(k))
    return np.clip(m.mesh.entropy / hi, 0.0, 1.0).astype(np.float32), 0.0, hi, "nats"
  if mode == "confidence":
    lo = 1.0 / k
    t = (np.asarray(m.mesh.confidence, np.float64) - lo) / (1.0 - lo)
    return np.clip(t, 0.0, 1.0).astype(np.float32), lo, 1.0, ""
  raise ValueError(f"{mode!r} is not a continuous colour mode")


def mesh_colors(m: ViewMap, mode: str, palette: np.ndarray) -> np.ndarray:
  """`(P, 3) uint8` colour of every mesh vertex of `m` in colour mode `mode`.

  Class: the palette; entropy and confidence: `mesh_scalar` on the viewer's colour scale;
  correct: right where the vertex's label is the GT label of the semantic voxel it lies in,
  wrong where it is another, unscored where the GT (or the map) has no voxel there. Vertices
  without a semantic voxel are grey (`NO_VOXEL_COLOR`) in the other modes.

  Raises:
    ValueError: no mesh, a mode the mesh does not support, a palette of the wrong size.
  """
  _check_mesh_mode(m, mode)
  mesh = m.mesh
  labelled = mesh.labels >= 0
  if mode == "correct":
    gt = m.mesh_gt_labels
    out = np.empty((mesh.num_vertices, 3), np.uint8)
    out[:] = UNSCORED_COLOR
    scored = gt >= 0
    out[scored & (gt == mesh.labels)] = RIGHT_COLOR
    out[scored & (gt != mesh.labels)] = WRONG_COLOR
    return out
  if mode == "class":
    palette = np.asarray(palette, np.uint8)
    if palette.ndim != 2 or palette.shape[1] != 3 or len(palette) < m.num_classes:
      raise ValueError(f"palette must be (K ≥ {m.num_classes}, 3); got {palette.shape}")
    colors = palette[np.maximum(mesh.labels, 0)]
  else:
    colors = colormap(mesh_scalar(m, mode)[0])
  colors[~labelled] = NO_VOXEL_COLOR
  return colors


def mesh_legend(m: ViewMap, mode: str, palette: np.ndarray) -> list:
  """`[(text, (r, g, b) or None for a heading), ...]` explaining `mesh_colors(m, mode, ...)`;
  counts are of mesh vertices."""
  _check_mesh_mode(m, mode)
  mesh = m.mesh
  unlabelled = int(np.sum(mesh.labels < 0))
  no_voxel = [(f"no semantic voxel ({unlabelled})", NO_VOXEL_COLOR)] if unlabelled else []
  if mode == "class":
    counts = np.bincount(mesh.labels[mesh.labels >= 0], minlength=m.num_classes)
    return ([("mesh: vertices per class", None)]
            + [(f"{name} ({int(n)})", tuple(int(c) for c in palette[i]))
               for i, (name, n) in enumerate(zip(m.class_names, counts))] + no_voxel)
  if mode == "correct":
    gt = m.mesh_gt_labels
    scored = gt >= 0
    right = int(np.sum(scored & (gt == mesh.labels)))
    wrong = int(np.sum(scored)) - right
    acc = f", accuracy {100 * right / max(right + wrong, 1):.1f} %"
    return [("mesh: vertices vs GT of their voxel", None),
            (f"right ({right}{acc})", RIGHT_COLOR), (f"wrong ({wrong})", WRONG_COLOR),
            (f"not in GT ({mesh.num_vertices - right - wrong})", UNSCORED_COLOR)]
  _, lo, hi, unit = mesh_scalar(m, mode)
  stops = np.linspace(0.0, 1.0, 5)
  heading = ("mesh: entropy" if mode == "entropy" else
             "mesh: confidence = max posterior probability")
  return ([(heading, None)]
          + [(f"{v:.3g} {unit}".rstrip(), tuple(int(x) for x in c))
             for v, c in zip(lo + stops * (hi - lo), colormap(stops))] + no_voxel)


def mesh_face_mask(m: ViewMap, *, hidden_classes: Iterable[int] = (),
                   max_height: Optional[float] = None, up_axis: int = 2) -> np.ndarray:
  """`(F,) bool`: mesh faces whose class (at the face's centroid, `Mesh.face_labels`) is not
  hidden and whose centroid is at most `max_height` metres along the up axis (None: no cut).
  Faces without a semantic voxel have no class and are kept."""
  if m.mesh is None:
    raise ValueError(f"{m.name}: this map has no mesh")
  hidden = np.asarray(sorted(set(int(c) for c in hidden_classes)), np.int64)
  if np.any((hidden < 0) | (hidden >= m.num_classes)):
    raise ValueError(f"hidden classes must be in [0, {m.num_classes}); got {hidden.tolist()}")
  if up_axis not in (0, 1, 2):
    raise ValueError(f"up_axis must be 0, 1 or 2; got {up_axis}")
  mesh = m.mesh
  keep = ~np.isin(mesh.face_labels, hidden)
  if max_height is not None:
    keep &= mesh.vertices[mesh.faces][:, :, up_axis].mean(axis=1) <= max_height
  return keep


def coarse_voxels(m: ViewMap, *, max_voxels: int = DEFAULT_PREVIEW_VOXELS) -> ViewMap:
  """`m` with its voxels thinned to at most `max_voxels` on a coarser grid: the first picture
  of a map whose mesh is being prepared. The grid's cells are f = 2, 4, 8 … voxels a side (the
  smallest f that fits), aligned on the voxel grid; each keeps the one of its voxels nearest
  the cell's centre (the first in the map's order of those as near), with all its values
  (class, entropy, ᾱ, hits, GT), moved to the cell's centre, and `voxel_size` is the cell's
  edge. So the coarse cubes cover every voxel of `m`, and each shows the class of one of
  them. A map of at most `max_voxels` voxels is returned as it is.
  """
  if max_voxels < 1:
    raise ValueError(f"max_voxels must be ≥ 1; got {max_voxels}")
  if len(m) <= max_voxels:
    return m
  keys = np.round(np.asarray(m.centers, np.float64) / m.voxel_size - 0.5).astype(np.int64)
  f = 1
  while True:
    f *= 2
    cells = np.floor_divide(keys, f)
    # Twice the offset from the cell's centre, in voxels: odd integers, so ties are exact.
    off_centre = np.sum((2 * (keys - cells * f) - (f - 1)) ** 2, axis=1)
    low = cells.min(axis=0)
    span = cells.max(axis=0) - low + 1
    code = ((cells[:, 0] - low[0]) * span[1] + cells[:, 1] - low[1]) * span[2] + (
        cells[:, 2] - low[2])
    order = np.lexsort((off_centre, code))   # stable: equals stay in the map's order
    first = np.ones(len(order), bool)
    first[1:] = code[order[1:]] != code[order[:-1]]
    if first.sum() <= max_voxels:
      break
  keep = order[first]
  cell = m.voxel_size * f
  pick = lambda x: None if x is None else np.asarray(x)[keep]
  return dataclasses.replace(
      m, voxel_size=float(cell), centers=((cells[keep] + 0.5) * cell).astype(np.float32),
      labels=pick(m.labels), hits=pick(m.hits), entropy=pick(m.entropy),
      confidence=pick(m.confidence), gt_labels=pick(m.gt_labels))


def mesh_part(m: ViewMap, keep: np.ndarray, colors: np.ndarray) -> tuple:
  """The faces of `m.mesh` where `keep`, with only the vertices they use (renumbered).

  Returns:
    `(vertices (p, 3) float32, faces (f, 3) int32, colors (p, 3) uint8, normals (p, 3)
    float32)`.
  """
  mesh = m.mesh
  faces = mesh.faces[np.asarray(keep, bool)]
  used = np.zeros(mesh.num_vertices, bool)
  used[faces.reshape(-1)] = True
  index = (np.cumsum(used) - 1).astype(np.int32)
  return (mesh.vertices[used], index[faces].astype(np.int32), np.asarray(colors)[used],
          mesh.normals[used])


def mesh_glb(vertices: np.ndarray, faces: np.ndarray, colors: np.ndarray,
             normals: Optional[np.ndarray] = None) -> bytes:
  """A binary glTF (GLB) of a mesh with per-vertex sRGB `colors (p, 3) uint8`, for the page.

  Written by trimesh, with one material added: not metallic and fully rough (glTF's default
  material is metallic, which looks black without an environment map), single-sided (faces
  point to where the camera was, so the inside of a room shows through its walls from outside).
  The colours are written as they are: the viewer's page takes a GLB's vertex colours for sRGB
  (as it does the cubes' colours), so a linear-light conversion would darken them twice (the
  browser test compares the lit mesh with the lit cubes).
  """
  import json
  import struct
  import trimesh
  rgba = np.concatenate([np.asarray(colors, np.uint8),
                         np.full((len(colors), 1), 255, np.uint8)], axis=1)
  kwargs = {} if normals is None else {"vertex_normals": np.asarray(normals, np.float64)}
  glb = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64),
                        vertex_colors=rgba, process=False, **kwargs).export(file_type="glb")
  json_length, json_type = struct.unpack_from("<II", glb, 12)
  if glb[:4] != b"glTF" or json_type != 0x4E4F534A:
    raise ValueError("trimesh wrote an unexpected GLB layout")
  doc = json.loads(glb[20:20 + json_length])
  doc["materials"] = [{"name": "vertex_colors", "doubleSided": False,
                       "pbrMetallicRoughness": {"baseColorFactor": [1.0, 1.0, 1.0, 1.0],
                                                "metallicFactor": 0.0,
                                                "roughnessFactor": 1.0}}]
  for mesh in doc.get("meshes", []):
    for primitive in mesh["primitives"]:
      primitive["material"] = 0
  text = json.dumps(doc, separators=(",", ":")).encode()
  text += b" " * (-len(text) % 4)
  rest = glb[20 + json_length:]
  return (struct.pack("<4sII", b"glTF", 2, 20 + len(text) + len(rest))
          + struct.pack("<II", len(text), 0x4E4F534A) + text + rest)


# Voxels as cubes or points --------------------------------------------------------------------


DRAW_CHOICES = ("auto", "cubes", "points")


def representation(num_voxels: int, max_cubes: int, choice: str = "auto") -> str:
  """How to draw `num_voxels` voxels: "cubes" or "points".

  `choice` "auto" draws cubes up to `max_cubes` voxels and points beyond (a 10⁶-voxel map
  stays smooth: a point costs one vertex, a cube 12 triangles); "cubes" / "points" force one.
  """
  if max_cubes < 0 or num_voxels < 0:
    raise ValueError(f"counts must be ≥ 0; got num_voxels={num_voxels}, max_cubes={max_cubes}")
  if choice not in DRAW_CHOICES:
    raise ValueError(f"choice must be one of {list(DRAW_CHOICES)}; got {choice!r}")
  if choice != "auto":
    return choice
  return "cubes" if num_voxels <= max_cubes else "points"


def height_range(maps: Sequence[ViewMap], up_axis: int = 2) -> tuple:
  """`(lo, hi)`: the lowest and highest voxel centre (or mesh vertex) of all maps along the up
  axis."""
  heights = [m.centers[:, up_axis] for m in maps if len(m)]
  heights += [m.mesh.vertices[:, up_axis] for m in maps if m.mesh is not None]
  if not heights:
    return 0.0, 1.0
  all_h = np.concatenate(heights)
  return float(all_h.min()), float(all_h.max())


def initial_camera(maps: Sequence[ViewMap], up_axis: int = 2) -> tuple:
  """`(position, look_at)` of a camera that sees all maps from above one corner."""
  points = [m.centers for m in maps if len(m)]
  points += [m.mesh.vertices for m in maps if m.mesh is not None]
  if not points:
    return np.array([3.0, -3.0, 3.0]), np.zeros(3)
  pts = np.concatenate(points)
  lo, hi = pts.min(axis=0), pts.max(axis=0)
  center = (lo + hi) / 2
  extent = max(float(np.linalg.norm(hi - lo)), 1.0)
  direction = np.array([-0.55, -0.75, 0.0])
  direction[up_axis] = 0.9
  direction /= np.linalg.norm(direction)
  return center + 0.8 * extent * direction, center


def frustum_indices(num_poses: int, max_frustums: int) -> np.ndarray:
  """Up to `max_frustums` evenly spread frame indices (first and last included)."""
  if max_frustums < 1:
    raise ValueError(f"max_frustums must be ≥ 1; got {max_frustums}")
  if num_poses <= max_frustums:
    return np.arange(num_poses)
  return np.unique(np.round(np.linspace(0, num_poses - 1, max_frustums)).astype(np.int64))


def frustum_shape(camera: Optional[dict]) -> tuple:
  """`(vertical fov in radians, aspect W/H)` of the saved camera (60°, 4:3 when unknown)."""
  if not camera:
    return float(np.deg2rad(60.0)), 4.0 / 3.0
  return (float(2 * np.arctan2(camera["height"] / 2, camera["fy"])),
          float(camera["width"] / camera["height"]))
