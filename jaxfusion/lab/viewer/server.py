"""The web viewer of saved maps, built on viser (the optional `viewer` extra).

`MapViewer` serves one page: the mesh of the chosen map (when it has a geometry layer) and/or
its voxels as cubes (points beyond `max_cubes`), a colour mode with its legend, toggles to hide
classes, a height cut, and the camera trajectory as frustums. Switching maps replaces the mesh
and voxels only, so the camera stays where the user left it. What is drawn is computed by
`scene_data`; this module only shows it.

Maps loaded without their meshes (`scene_data.load_maps(..., mesh=False)`, as `serve` does)
are served at once: a coarse preview of their voxels is drawn while a background thread makes
the meshes, once for every page (viser replays the scene to each page that opens). A progress
line at the top of the panel, and the `progress` callback (the command line), say what is
being done.
"""

import dataclasses
import signal
import threading
import time
from typing import Callable, Optional, Sequence

import numpy as np
import viser
import viser.transforms as vtf

from jaxfusion.lab.viewer import scene_data as sd

_UP_AXIS = 2   # jaxfusion's worlds are z-up
_BOX_VERTICES = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5)
                          for z in (-0.5, 0.5)], np.float32)
# 12 outward-facing triangles of the unit cube over _BOX_VERTICES (index = 4x + 2y + z).
_BOX_FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                       [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]],
                      np.uint32)


class MapViewer:
  """A running viewer of maps (of one or more sequences) with the same class list.

  Attributes:
    server: the `viser.ViserServer`.
    controls: the GUI handles by role — "sequence", "map", "show", "color", "draw"
      (dropdowns), "height" (slider), "trajectory" (checkbox) and "hide" (class name →
      checkbox). Setting a handle's `value` from Python redraws the scene as a click in the
      page does. "show" (mesh / voxels / both) is visible only when some map has a mesh; a
      map without one shows its voxels whatever it says.
    last_drawn: what the last redraw drew: "map" (path), "mode", "kind" ("cubes", "points",
      or None when the voxels are not shown) and "count" (voxels drawn); for a map with a
      mesh, or one being prepared, also "mesh" (faces drawn, 0 when the mesh is not shown or
      not there yet); while it is being prepared, also "preview" (the preview's cubes drawn).
    progress: the progress lines shown so far, oldest first (the last one is in the panel).
    ready: a `threading.Event` set once every map's mesh is prepared and drawn (at once when
      none was pending).

  While a map's mesh is being prepared, its place is taken by a coarse preview of its voxels
  (`scene_data.coarse_voxels`, at most `preview_voxels` cubes), coloured by class, entropy or
  right / wrong as the mesh would be (by class in the confidence mode); "Show" voxels or
  mesh + voxels draws the voxels themselves instead.

  Args:
    maps: the maps (of one class list); those loaded with `mesh=False` get their meshes
      in the background.
    preview_voxels: the most cubes of the preview shown while a mesh is being prepared.
    progress: also called with each progress line (e.g. `print`).
    prepare: start making the pending meshes at once (False: when `prepare_meshes` is
      called, e.g. after the page's address is printed).
  """

  def __init__(self, maps: Sequence[sd.ViewMap], *, host: str = "127.0.0.1", port: int = 8080,
               max_cubes: int = sd.DEFAULT_MAX_CUBES, max_frustums: int = 40,
               preview_voxels: int = sd.DEFAULT_PREVIEW_VOXELS,
               progress: Optional[Callable[[str], None]] = None, prepare: bool = True,
               verbose: bool = False):
    if not maps:
      raise ValueError("MapViewer needs at least one map")
    sd.check_same_classes(maps)
    if max_cubes < 0:
      raise ValueError(f"max_cubes must be ≥ 0; got {max_cubes}")
    if preview_voxels < 1:
      raise ValueError(f"preview_voxels must be ≥ 1; got {preview_voxels}")
    self._preview_voxels = int(preview_voxels)
    self._previews = {}   # path → coarse_voxels of a map whose mesh is being prepared
    self._on_progress = progress
    self.progress = []
    self.ready = threading.Event()
    self._stopped = False
    self._preparing = None   # the thread making the pending meshes
    self._maps = sd.by_sequence(maps)
    self._all = list(maps)
    self._palette = sd.class_palette(maps[0].class_names)
    self._max_cubes = int(max_cubes)
    self._max_frustums = int(max_frustums)
    self._lock = threading.RLock()
    self._trajectory_of = None   # path of the map whose trajectory is drawn
    self._trajectory_root = None
    self._mesh_drawn = None   # what the mesh node shows now (skips resending the same GLB)
    self._quiet = False   # True while _map_changed sets the colour control (it redraws after)
    self.last_drawn = {}
    self.server = viser.ViserServer(host=host, port=port, verbose=verbose)
    scene = self.server.scene
    scene.set_up_direction("+z")
    scene.configure_environment_map(hdri=None)
    scene.configure_default_lights(enabled=False)
    # Soft light from above one corner: faces stay distinguishable, colours near the palette.
    scene.add_light_ambient("/light/ambient", intensity=0.55)
    scene.add_light_directional("/light/sun", intensity=0.9, position=(-1.0, -2.0, 3.0),
                                cast_shadow=False)
    position, look_at = sd.initial_camera(self._all, _UP_AXIS)
    self.server.initial_camera.position = tuple(float(x) for x in position)
    self.server.initial_camera.look_at = tuple(float(x) for x in look_at)
    self.server.initial_camera.up = (0.0, 0.0, 1.0)
    self._build_gui()
    self.redraw()
    if not any(m.mesh_pending for m in self._all):
      self.ready.set()
    elif prepare:
      self.prepare_meshes()

  @property
  def url(self) -> str:
    return f"http://{self.server.get_host()}:{self.server.get_port()}"

  def current_map(self) -> sd.ViewMap:
    return self._maps[self.controls["sequence"].value][self.controls["map"].value]

  def _build_gui(self):
    gui = self.server.gui
    sequences = list(self._maps)
    first = self._maps[sequences[0]]
    c = {}
    gui.add_markdown(f"**jaxfusion** · {len(self._all)} map(s)")
    self._progress = gui.add_markdown("")
    c["sequence"] = gui.add_dropdown("Sequence", sequences, initial_value=sequences[0],
                                     visible=len(sequences) > 1)
    c["map"] = gui.add_dropdown("Map", list(first), initial_value=next(iter(first)))
    any_mesh = any(m.mesh is not None or m.mesh_pending for m in self._all)
    c["show"] = gui.add_dropdown("Show", list(sd.SHOW_CHOICES),
                                 initial_value="mesh" if any_mesh else "voxels",
                                 visible=any_mesh,
                                 hint="the surface of the geometry layer, the semantic voxels, "
                                      "or both (maps without a mesh show their voxels)")
    titles = sd.mode_titles(first[next(iter(first))], c["show"].value)
    self._last_titles = titles
    c["color"] = gui.add_dropdown("Colour by", list(titles.values()),
                                  initial_value=titles["class"])
    c["draw"] = gui.add_dropdown("Draw as", list(sd.DRAW_CHOICES), initial_value="auto",
                                 hint=f"auto: cubes up to {self._max_cubes} voxels, then points")
    self._legend = gui.add_html("")
    self._status = gui.add_markdown("")
    lo, hi = sd.height_range(self._all, _UP_AXIS)
    step = min(m.voxel_size for m in self._all)
    self._height_max = hi + step
    c["height"] = gui.add_slider("Height cut (m)", min=float(np.floor(lo / step) * step),
                                 max=float(self._height_max), step=float(step),
                                 initial_value=float(self._height_max))
    c["trajectory"] = gui.add_checkbox("Camera trajectory", initial_value=True,
                                       visible=any(m.poses is not None for m in self._all))
    c["hide"] = {}
    with gui.add_folder("Hide classes", expand_by_default=False):
      for name in first[next(iter(first))].class_names:
        c["hide"][name] = gui.add_checkbox(name, initial_value=False)
    self.controls = c

    c["sequence"].on_update(lambda _: self._sequence_changed())
    c["map"].on_update(lambda _: self._map_changed())
    c["show"].on_update(lambda _: self._map_changed())
    for handle in [c["color"], c["draw"], c["height"], c["trajectory"], *c["hide"].values()]:
      handle.on_update(lambda _: self._control_changed())

  def _sequence_changed(self):
    with self._lock:
      names = list(self._maps[self.controls["sequence"].value])
      if self.controls["map"].value in names:
        self.controls["map"].options = names
        self._map_changed()
      else:
        self.controls["map"].options = names   # moves the value, which calls _map_changed

  def _map_changed(self):
    """The map or what is shown changed: offer the colour modes of what is shown now (the
    mode is kept when it is still offered, under its new title where that changes; else it
    falls back to class), then redraw once."""
    with self._lock:
      mode = self._mode_of_title(self._last_titles, self.controls["color"].value)
      titles = sd.mode_titles(self.current_map(), self.controls["show"].value)
      self._last_titles = titles
      color = self.controls["color"]
      # Changing the options can move the value (to the first option) and a new title moves
      # it again: each move would redraw (and resend the mesh) on its own.
      self._quiet = True
      try:
        if tuple(color.options) != tuple(titles.values()):
          color.options = list(titles.values())
        color.value = titles.get(mode, titles["class"])
      finally:
        self._quiet = False
      self.redraw()

  def _control_changed(self):
    with self._lock:
      if not self._quiet:
        self.redraw()

  @staticmethod
  def _mode_of_title(titles: dict, title: str) -> Optional[str]:
    return next((k for k, v in titles.items() if v == title), None)

  def _mode(self, m: sd.ViewMap) -> str:
    titles = sd.mode_titles(m, self.controls["show"].value)
    mode = self._mode_of_title(titles, self.controls["color"].value)
    return mode if mode is not None else "class"

  def redraw(self):
    """Draws the current map with the current colour mode, classes and height cut."""
    with self._lock:
      m = self.current_map()
      mode = self._mode(m)
      hidden = [i for i, box in enumerate(self.controls["hide"].values()) if box.value]
      cut = float(self.controls["height"].value)
      max_height = None if cut >= self._height_max else cut
      show_mesh, show_voxels = sd.shown_layers(m, self.controls["show"].value)
      self.controls["draw"].visible = show_voxels
      pending = show_mesh and m.mesh is None
      faces = (self._draw_mesh(m, mode, hidden, max_height) if show_mesh and not pending
               else self._remove_mesh())
      legend, status = [], []
      if pending and not show_voxels:
        preview = self._preview(m)
        # Entropy and right/wrong mean the same on voxels and mesh; confidence does not.
        preview_mode = mode if mode in ("entropy", "correct") and mode in sd.color_modes(
            preview) else "class"
        _, shown = self._draw_voxels(preview, preview_mode, hidden, max_height,
                                     node="/preview", kind="cubes")
        legend += sd.legend(m, preview_mode, self._palette)
        status.append(f"mesh: being prepared; meanwhile {shown} voxels of "
                      f"{preview.voxel_size:g} m (a coarse preview of {len(m)})")
      else:
        self.server.scene.remove_by_name("/preview")
        shown = 0
      if pending and show_voxels:
        status.append("mesh: being prepared")
      elif show_mesh and not pending:
        legend += sd.mesh_legend(m, mode, self._palette)
        status.append(f"mesh: {faces} of {m.mesh.num_faces} faces")
      if show_voxels:
        kind, count = self._draw_voxels(m, mode, hidden, max_height)
        voxel_legend = sd.legend(m, mode, self._palette)
        legend += [("voxels", None), *voxel_legend] if show_mesh and not pending else (
            voxel_legend)
        status.append(f"{count} of {len(m)} voxels ({m.voxel_size:g} m), drawn as {kind}")
      else:
        self.server.scene.remove_by_name("/voxels")
        kind, count = None, 0
      self._legend.content = sd.legend_html(legend)
      self._status.content = "; ".join(status)
      self._draw_trajectory(m)
      self.last_drawn = {"map": m.path, "mode": mode, "kind": kind, "count": int(count)}
      if m.mesh is not None or m.mesh_pending:
        self.last_drawn["mesh"] = int(faces)
      if m.mesh_pending:
        self.last_drawn["preview"] = int(shown)

  def _draw_mesh(self, m: sd.ViewMap, mode: str, hidden: list, max_height) -> int:
    """Draws the mesh's visible faces with per-vertex colours; returns how many."""
    key = (m.path, mode, tuple(hidden), max_height)
    keep = sd.mesh_face_mask(m, hidden_classes=hidden, max_height=max_height,
                             up_axis=_UP_AXIS)
    if key == self._mesh_drawn:
      return int(keep.sum())
    vertices, faces, colors, normals = sd.mesh_part(m, keep,
                                                    sd.mesh_colors(m, mode, self._palette))
    if len(faces) == 0:
      self._remove_mesh()
    else:
      self.server.scene.add_glb("/mesh", sd.mesh_glb(vertices, faces, colors, normals),
                                cast_shadow=False, receive_shadow=False)
    self._mesh_drawn = key
    return int(len(faces))

  def _remove_mesh(self) -> int:
    self.server.scene.remove_by_name("/mesh")
    self._mesh_drawn = None
    return 0

  def _preview(self, m: sd.ViewMap) -> sd.ViewMap:
    if m.path not in self._previews:
      self._previews[m.path] = sd.coarse_voxels(m, max_voxels=self._preview_voxels)
    return self._previews[m.path]

  def _draw_voxels(self, m: sd.ViewMap, mode: str, hidden: list, max_height, *,
                   node: str = "/voxels", kind: Optional[str] = None) -> tuple:
    """Draws the visible voxels at `node` as cubes or points (`kind`; None: as the "Draw as"
    control says); returns `(kind, count)`."""
    keep = sd.visible_mask(m, hidden_classes=hidden, max_height=max_height, up_axis=_UP_AXIS)
    colors = sd.voxel_colors(m, mode, self._palette)[keep]
    centers = m.centers[keep]
    if kind is None:
      kind = sd.representation(len(centers), self._max_cubes, self.controls["draw"].value)
    scene = self.server.scene
    if len(centers) == 0:
      scene.remove_by_name(node)
    elif kind == "cubes":
      scene.add_batched_meshes_simple(
          node, _BOX_VERTICES * m.voxel_size, _BOX_FACES,
          batched_wxyzs=np.broadcast_to(np.array([1.0, 0.0, 0.0, 0.0], np.float32),
                                        (len(centers), 4)),
          batched_positions=centers, batched_colors=colors, flat_shading=True, lod="off",
          cast_shadow=False, receive_shadow=False)
    else:
      scene.add_point_cloud(node, centers, colors, point_size=m.voxel_size,
                            point_shape="square", point_shading="flat", precision="float32")
    return kind, int(len(centers))

  def _draw_trajectory(self, m: sd.ViewMap):
    """Frustums along the map's saved camera path, under one node the checkbox hides."""
    show = bool(self.controls["trajectory"].value)
    scene = self.server.scene
    if self._trajectory_of != m.path:
      self._trajectory_of = m.path
      if self._trajectory_root is not None:
        self._trajectory_root.remove()
        self._trajectory_root = None
      if m.poses is None:
        return
      poses = m.poses
      extent = float(np.linalg.norm(np.ptp(m.centers, axis=0))) if len(m) else 1.0
      fov, aspect = sd.frustum_shape(m.camera)
      self._trajectory_root = scene.add_frame("/trajectory", show_axes=False, visible=show)
      for i in sd.frustum_indices(len(poses), self._max_frustums):
        scene.add_camera_frustum(
            f"/trajectory/frame_{int(i):04d}", fov=fov, aspect=aspect,
            scale=max(0.02 * extent, 2 * m.voxel_size), color=(40, 40, 40),
            wxyz=vtf.SO3.from_matrix(poses[i, :3, :3].astype(np.float64)).wxyz,
            position=poses[i, :3, 3].astype(np.float64))
      if len(poses) > 1:
        path = poses[:, :3, 3]
        scene.add_line_segments("/trajectory/path", np.stack([path[:-1], path[1:]], axis=1),
                                (230, 120, 20), thickness=max(0.004 * extent, 0.005))
    if self._trajectory_root is not None:
      self._trajectory_root.visible = show

  def _report(self, line: str):
    """Shows `line` as the panel's progress line and passes it to the `progress` callback."""
    self.progress.append(line)
    if not self._stopped:
      self._progress.content = f"*{line}*" if line.endswith("…") else line
    if self._on_progress is not None:
      self._on_progress(line)

  def _replace_map(self, old: sd.ViewMap, new: sd.ViewMap):
    """Puts `new` where `old` was and redraws when it is the map shown."""
    with self._lock:
      if self._stopped:
        return
      self._maps[old.sequence][old.name] = new
      self._all = [new if m is old else m for m in self._all]
      if not new.mesh_pending:
        self._previews.pop(new.path, None)
      if self.current_map() is new:
        self._map_changed()

  def prepare_meshes(self):
    """Starts making the pending meshes in a background thread (once; `ready` is set when
    done), the shown map's first."""
    with self._lock:
      if self._preparing is not None or self.ready.is_set():
        return
      pending = sum(m.mesh_pending for m in self._all)
      self._report(f"preparing the mesh of {pending} map(s); a coarse preview of the voxels is "
                   "shown meanwhile …")
      self._preparing = threading.Thread(target=self._prepare_meshes,
                                         name="jaxfusion-view-meshes", daemon=True)
      self._preparing.start()

  def _prepare_meshes(self):
    start = time.monotonic()
    shown = self.current_map()
    pending = sorted((m for m in self._all if m.mesh_pending), key=lambda m: m is not shown)
    failed = []
    try:
      for i, m in enumerate(pending):
        if self._stopped:
          return
        what = m.name if len(pending) == 1 else f"{m.name} ({i + 1} of {len(pending)})"
        try:
          full = sd.prepare_mesh(m, progress=lambda line, w=what: self._report(
              f"{w}: preparing mesh: {line}"))
        except Exception as e:   # pylint: disable=broad-except
          # Said in the page and on the command line (not lost in a thread); the map shows
          # its voxels, and the other maps' meshes are still made.
          failed.append(f"{what}: preparing the mesh failed: {type(e).__name__}: {e}")
          self._report(failed[-1])
          full = dataclasses.replace(m, mesh_source=None)
        if full.mesh is not None:
          self._report(f"{what}: sending mesh: {_thousands(full.mesh.num_faces)} faces …")
        self._replace_map(m, full)
      if not self._stopped:
        self._report(f"ready: {len(pending) - len(failed)} mesh(es) prepared in "
                     f"{time.monotonic() - start:.1f} s"
                     + (f"; {len(failed)} failed, the first: {failed[0]}" if failed else ""))
    finally:
      self.ready.set()

  def stop(self):
    with self._lock:
      self._stopped = True
    self.server.stop()


def _thousands(n: int) -> str:
  """`412345` → "412 k" (counts of faces in progress lines)."""
  return f"{n / 1000:.0f} k" if n >= 10_000 else str(n)


def serve(paths: Sequence[str], *, host: str = "127.0.0.1", port: int = 8080,
          max_cubes: int = sd.DEFAULT_MAX_CUBES, duration: Optional[float] = None) -> None:
  """Loads the maps named by `paths`, serves them, and blocks until Ctrl-C (or `duration` s
  after the address is printed). The page is served once the voxels are loaded; the meshes are
  made after, in the background (`MapViewer.prepare_meshes`). Every stage is printed as one
  line with the seconds since the start.

  Raises:
    FileNotFoundError / ValueError: a bad path, a file that is not a map, maps of different
      class lists (see `scene_data.load_maps`).
  """
  start = time.monotonic()

  def say(line):
    print(f"[{time.monotonic() - start:5.1f} s] {line}", flush=True)

  maps = sd.load_maps(paths, mesh=False, progress=say)
  sequences = len({m.sequence for m in maps})
  viewer = MapViewer(maps, host=host, port=port, max_cubes=max_cubes, progress=say,
                     prepare=False)
  print(f"viewing {len(maps)} map(s) of {sequences} sequence(s) at {viewer.url}  "
        "(Ctrl-C stops)", flush=True)
  viewer.prepare_meshes()
  serving = time.monotonic()
  # A process started with SIGINT ignored (a background job of a non-interactive shell, or a
  # parent that ignores it) inherits that, and Python then installs no KeyboardInterrupt
  # handler: Ctrl-C / `kill -INT` would be lost and the server would run forever. The viewer
  # promises that Ctrl-C stops it, so it takes SIGINT for as long as it serves.
  previous = None
  if threading.current_thread() is threading.main_thread():
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
  try:
    while duration is None or time.monotonic() - serving < duration:
      time.sleep(0.2)
  except KeyboardInterrupt:
    pass
  finally:
    viewer.stop()
    if previous is not None:
      signal.signal(signal.SIGINT, previous)
  print("viewer stopped", flush=True)
