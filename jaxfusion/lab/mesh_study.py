"""`jaxfusion mesh-study`: the maps' meshes judged against the embedded world's true surface.

A second view of the paper's question, beside the voxel mIoU of `jaxfusion study`: for every
sequence of the grid (the study's held-out layouts, environments, trajectories and shifts), the
front end runs once (cached, shareable with the study), the geometry layer (5 cm, τ = 4 voxels)
is fused once with the first rule and shared by every rule's map, and each rule's map gives a
mesh whose vertices carry the rule's class (`jf.extract_mesh`). Against the true surface
(`datasets.surfaces`: exact ray-cast hits on the primitives, thinned to 1 cm, where the
sequence's cameras see them):

- geometry (one mesh per sequence): accuracy, completeness and Chamfer-L1 in cm, precision,
  recall and F-score at 5 and 2 cm, both surfaces sampled evenly (`jaxfusion.surface_metrics`);
- semantics (one per rule): each vertex's class against the class of its nearest true surface
  point, weighted by the vertex's share of the mesh area; the area-weighted confusions are
  summed over sequences (a vertex with no semantic voxel counts as wrong) and give the mesh
  mIoU and accuracy, beside the voxel mIoU of the same maps;
- differences from Bayes, with 95 % paired bootstrap intervals over sequences (`lab.stats`).

Writes `mesh_study.md`, `.json`, `mesh_study.png` (mesh vs voxel mIoU per rule) and
`mesh_<sequence>.png` (the first sequence's mesh coloured by the true class and by three rules).
"""

import argparse
import dataclasses
import json
import os
import time
from typing import Optional

import numpy as np
from tqdm.auto import tqdm

import jaxfusion as jf
from jaxfusion import datasets
from jaxfusion import io
from jaxfusion import learn
from jaxfusion import metrics
from jaxfusion import surface_metrics
from jaxfusion.datasets import surfaces
from jaxfusion.lab import config as config_lib
from jaxfusion.lab import demo
from jaxfusion.lab import figures
from jaxfusion.lab import flags
from jaxfusion.lab import frontend
from jaxfusion.lab import stats
from jaxfusion.lab import study

LEARNED = study.LEARNED
# More fitted rows (`--variant TAG=PARAMS_JSON`) are named "fitted:<tag>".
FITTED_PREFIX = "fitted:"
GEOMETRY_KEYS = ("accuracy", "completeness", "chamfer_l1", "precision@0.05", "recall@0.05",
                 "fscore@0.05", "precision@0.02", "recall@0.02", "fscore@0.02")
CM_KEYS = ("accuracy", "completeness", "chamfer_l1")
MESH_SAMPLE_SPACING = 0.01   # metres between the mesh's samples, as the true surface's


@dataclasses.dataclass(frozen=True)
class MeshStudyConfig:
  """What the mesh study runs.

  Attributes:
    run: the sequences, front end and rules (`config.RunConfig`; default the study's grid).
    geometry: the geometry layer (`tsdf.TSDFConfig`; default `demo.GEOMETRY`).
    learned: parameters of `rules.learned`, fused on the MC moments as a seventh row (None: the
      six paper rules only).
    learned_source: where `learned` came from, for the report.
    fitted: more fitted rows, `((tag, family, params), …)` (`--variant TAG=PARAMS_JSON`: GLFS,
      a learned rule or a member of the rule family), each a row "fitted:<tag>".
    surface_spacing: thinning grid of the true surface, metres.
    upsample: rays per pixel (per axis) of the true surface's ray cast.
    num_resamples: bootstrap resamples.
    confidence: interval coverage.
  """
  run: config_lib.RunConfig = dataclasses.field(default_factory=lambda: study.StudyConfig().run)
  geometry: jf.tsdf.TSDFConfig = demo.GEOMETRY
  learned: Optional[dict] = None
  learned_source: Optional[str] = None
  fitted: tuple = ()
  surface_spacing: float = surfaces.DEFAULT_SPACING
  upsample: int = surfaces.DEFAULT_UPSAMPLE
  num_resamples: int = stats.DEFAULT_RESAMPLES
  confidence: float = stats.DEFAULT_CONFIDENCE

  @classmethod
  def of(cls, quick: bool = False, **run) -> "MeshStudyConfig":
    """The full (or quick) mesh study with some run fields replaced (None: keep). The full one
    runs the study's grid; quick one office sequence at shifts 0 and 1, 12 frames at 60×80."""
    learned = run.pop("learned", None)
    source = run.pop("learned_source", None)
    fitted = tuple(run.pop("fitted", None) or ())
    num_resamples = run.pop("num_resamples", None)
    base = study.StudyConfig.quick().run if quick else study.StudyConfig().run
    if quick:
      base = dataclasses.replace(base, envs=("office",), shifts=(0.0, 1.0))
    out = cls(run=config_lib.replace(base, **run), learned=learned, learned_source=source,
              fitted=fitted)
    return dataclasses.replace(out, num_resamples=num_resamples) if num_resamples else out

  @property
  def rule_names(self) -> list:
    return (list(self.run.rules) + ([LEARNED] if self.learned is not None else [])
            + [FITTED_PREFIX + tag for tag, _, _ in self.fitted])

  def make_rule(self, name: str):
    if name == LEARNED:
      return jf.rules.learned(self.learned, aggregate=self.run.aggregate)
    for tag, family, params in self.fitted:
      if name == FITTED_PREFIX + tag:
        return learn.rule_of(family, params, aggregate=self.run.aggregate)
    return self.run.make_rule(name)

  def validate(self) -> "MeshStudyConfig":
    """Raises ValueError for an unusable configuration; returns self."""
    self.run.validate()
    if "bayes" not in self.run.rules:
      raise ValueError(f"rules must include 'bayes'; got {self.run.rules}")
    if not self.surface_spacing > 0:
      raise ValueError(f"surface_spacing must be positive; got {self.surface_spacing}")
    if int(self.num_resamples) < 1:
      raise ValueError(f"num_resamples must be at least 1; got {self.num_resamples}")
    return self


def geometry_scores(mesh, surface: dict, *, seed: int = 0) -> dict:
  """`surface_metrics.reconstruction_scores` of a mesh against a true surface, both sampled
  every `MESH_SAMPLE_SPACING` (the mesh: area-weighted random samples); plus its size."""
  points, _, _ = surface_metrics.sample_mesh(mesh.vertices, mesh.faces,
                                             spacing=MESH_SAMPLE_SPACING,
                                             rng=np.random.default_rng(seed))
  out = surface_metrics.reconstruction_scores(points, surface["points"])
  out.update(vertices=int(mesh.num_vertices), faces=int(mesh.num_faces),
             area_m2=float(surface_metrics.face_areas(mesh.vertices, mesh.faces).sum()))
  return out


def evaluate_sequence(sequence, predictions: dict, gt_voxels: dict, surface: dict,
                      config: MeshStudyConfig, *, ignore_label: Optional[int] = None) -> dict:
  """One sequence: the shared geometry's scores, and per rule the voxel confusion `(K, K)`
  (counts) and the mesh's padded area confusion `(K + 1, K + 1)` (m²;
  `surface_metrics.padded_confusion`), and the meshes (for the figure)."""
  k = predictions["mean"].shape[-1]
  geometry = surface_mesh = nearest = None
  voxel_cm, mesh_cm, meshes = {}, {}, {}
  for name in config.rule_names:
    state = demo.fuse_with_rule(sequence, predictions, config.make_rule(name), config.run,
                                geometry=config.geometry if geometry is None else None)
    if geometry is None:   # one geometry layer, one mesh: each rule only relabels it
      geometry = state.geometry
      surface_mesh = jf.extract_mesh(geometry)
      nearest = surface_metrics.nearest_points(surface_mesh.vertices, surface["points"])
    state = state.replace(geometry=geometry)
    voxel_cm[name] = metrics.evaluate_map(jf.read_map(state), gt_voxels, k)["confusion"]
    mesh = jf.label_mesh(surface_mesh, state)
    s = surface_metrics.mesh_semantic_scores(mesh.vertices, mesh.faces, mesh.labels,
                                             surface["points"], surface["labels"],
                                             num_classes=k, nearest=nearest,
                                             ignore_label=ignore_label)
    mesh_cm[name] = surface_metrics.padded_confusion(s["confusion"], s["unlabelled"])
    meshes[name] = mesh
  first = next(iter(meshes.values()))
  return {"geometry": geometry_scores(first, surface), "voxel_confusion": voxel_cm,
          "mesh_confusion": mesh_cm, "meshes": meshes}


def _padded_miou(confusions) -> np.ndarray:
  """mIoU of a stack of padded area confusions `(..., K + 1, K + 1)` (`stats.miou` averages
  over the classes present in the GT rows; the padded row is empty, so the "no label" column
  only enlarges each class's GT)."""
  return stats.miou(confusions)


def summarize(per_sequence: list, config: MeshStudyConfig) -> dict:
  """Pooled mIoU per rule (voxels, mesh), differences from Bayes with paired intervals over
  sequences, and the geometry's mean scores."""
  names = config.rule_names
  voxel = {n: np.stack([s["voxel_confusion"][n] for s in per_sequence]) for n in names}
  mesh = {n: np.stack([s["mesh_confusion"][n] for s in per_sequence]) for n in names}
  counts = stats.resample_counts(len(per_sequence), config.num_resamples, seed=0)
  rows = {}
  for n in names:
    _, _, mesh_acc = surface_metrics.iou_from_padded(mesh[n].sum(0))
    tag = f" ({n[len(FITTED_PREFIX):]})" if n.startswith(FITTED_PREFIX) else ""
    row = {"display": jf.rules.display_name(config.make_rule(n)) + tag,
           "voxel_miou": float(stats.miou(voxel[n].sum(0))),
           "mesh_miou": float(_padded_miou(mesh[n].sum(0))), "mesh_accuracy": mesh_acc,
           "mesh_iou": surface_metrics.iou_from_padded(mesh[n].sum(0))[0].tolist()}
    for kind, data, stat in (("voxel", voxel, stats.miou), ("mesh", mesh, _padded_miou)):
      d = stats.paired_difference(data[n], data["bayes"], stat, counts=counts,
                                  confidence=config.confidence)
      row[f"{kind}_vs_bayes"] = [d.estimate, d.low, d.high]
    rows[n] = row
  geometry = {key: float(np.mean([s["geometry"][key] for s in per_sequence]))
              for key in GEOMETRY_KEYS + ("vertices", "faces", "area_m2")}
  return {"rules": rows, "geometry": geometry, "sequences": len(per_sequence)}


def format_tables(summary: dict, config: MeshStudyConfig) -> str:
  """The report's Markdown tables: all sequences pooled (rules, then geometry), then mesh mIoU
  per shift when there are several."""
  text = _format_pooled(summary, config)
  if "by_shift" in summary:
    names = list(summary["rules"])
    shifts = list(summary["by_shift"])
    lines = ["", "| shift | " + " | ".join(summary["rules"][n]["display"] for n in names)
             + " | F@5 cm |", "|---" * (len(names) + 2) + "|"]
    for shift in shifts:
      part = summary["by_shift"][shift]
      cells = []
      for n in names:
        e, lo, hi = (100 * x for x in part["rules"][n]["mesh_vs_bayes"])
        cells.append(f"{100 * part['rules'][n]['mesh_miou']:.1f}"
                     + ("" if n == "bayes" else f" ({e:+.2f} [{lo:+.2f}, {hi:+.2f}])"))
      lines.append(f"| {shift} | " + " | ".join(cells)
                   + f" | {100 * part['geometry']['fscore@0.05']:.1f} |")
    text += "\n" + "\n".join(lines)
  return text


def _format_pooled(summary: dict, config: MeshStudyConfig) -> str:
  pct = config.confidence * 100
  lines = [f"| rule | voxel mIoU | mesh mIoU | mesh acc. | voxel − Bayes [{pct:.0f} %] | "
           f"mesh − Bayes [{pct:.0f} %] |", "|---|---|---|---|---|---|"]
  for row in summary["rules"].values():
    cells = [f"{100 * row['voxel_miou']:.1f}", f"{100 * row['mesh_miou']:.1f}",
             f"{100 * row['mesh_accuracy']:.1f}"]
    for kind in ("voxel", "mesh"):
      e, lo, hi = (100 * x for x in row[f"{kind}_vs_bayes"])
      cells.append(f"{e:+.2f} [{lo:+.2f}, {hi:+.2f}]")
    lines.append(f"| {row['display']} | " + " | ".join(cells) + " |")
  g = summary["geometry"]
  lines += ["", "| acc. cm | comp. cm | Chamfer-L1 cm | P@5 cm | R@5 cm | F@5 cm | P@2 cm | "
            "R@2 cm | F@2 cm | triangles |", "|---|---|---|---|---|---|---|---|---|---|",
            "| " + " | ".join([f"{100 * g[k]:.2f}" for k in CM_KEYS]
                             + [f"{100 * g[k]:.1f}" for k in GEOMETRY_KEYS[3:]]
                             + [f"{g['faces']:.0f}"]) + " |"]
  return "\n".join(lines)


def _figure_bars(path: str, summary: dict) -> None:
  plt = figures._pyplot()   # pylint: disable=protected-access
  rows = list(summary["rules"].values())
  x = np.arange(len(rows))
  fig, ax = plt.subplots(figsize=(7.5, 3.6))
  for offset, key, label in ((-0.2, "voxel_miou", "voxels (0.1 m)"),
                             (0.2, "mesh_miou", "mesh vertices, by area")):
    values = [100 * r[key] for r in rows]
    ax.bar(x + offset, values, width=0.4, label=label)
  ax.set_xticks(x, [r["display"] for r in rows], rotation=20)
  low = min(100 * min(r["voxel_miou"], r["mesh_miou"]) for r in rows)
  ax.set_ylim(max(0.0, low - 5), None)
  ax.set_ylabel("mIoU (%)")
  ax.set_title(f"mesh and voxel mIoU over {summary['sequences']} sequences")
  ax.legend(loc="lower right")
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def _figure_meshes(path: str, meshes: dict, surface: dict, colors: np.ndarray,
                   config: MeshStudyConfig) -> None:
  """The first sequence's mesh coloured by the class of the nearest true surface point, then
  by Bayes, D+R and the learned rule (whichever ran)."""
  from scipy.spatial import cKDTree   # pylint: disable=import-outside-toplevel
  grey = np.array(io.UNLABELLED_RGB, np.uint8)
  some = next(iter(meshes.values()))
  centroids = some.vertices[some.faces].mean(axis=1)
  _, nearest = cKDTree(surface["points"]).query(centroids)
  palette = lambda labels: np.where((labels >= 0)[:, None], colors[np.maximum(labels, 0)], grey)
  panels = {"True surface class": (some.vertices, some.faces,
                                   palette(surface["labels"][nearest]))}
  for name in ("bayes", "robust_dr", LEARNED):
    if name in meshes:
      m = meshes[name]
      panels[jf.rules.display_name(config.make_rule(name))] = (m.vertices, m.faces,
                                                               palette(m.face_labels))
  figures.mesh_views(path, panels)


def run_mesh_study(config: MeshStudyConfig, out_dir: str, *, cache_dir: Optional[str] = None,
                   checkpoint: Optional[str] = None, front_end=None) -> dict:
  """Runs the mesh study and writes its report, JSON and figures.

  Returns:
    dict with `summary`, `table`, `files`, `sequences` (per-sequence geometry scores) and
    `timing`.
  """
  config.validate()
  start = time.perf_counter()
  os.makedirs(out_dir, exist_ok=True)
  cache_dir = cache_dir or os.path.join(out_dir, "cache")
  front_end = front_end if front_end is not None else frontend.FrontEnd(checkpoint)
  colors = np.asarray(datasets.CLASS_COLORS, np.uint8)
  run = config.run
  per_sequence, files, names = [], [], []
  for (seed, env, traj), shift in tqdm(run.grid, desc="sequences"):
    seq = datasets.load_spec(datasets.SequenceSpec("synthetic", env, traj, run.domain),
                             num_frames=run.num_frames, height=run.height, width=run.width,
                             layout_seed=seed, shift=shift)
    gt = datasets.gt_voxel_labels(seq, voxel_size=run.voxel_size, capacity=run.capacity)
    surface = surfaces.sequence_surface(env, seed, shift, seq, domain=run.domain,
                                        spacing=config.surface_spacing,
                                        upsample=config.upsample)
    preds = frontend.cached_predictions(front_end, seq, layout_seed=seed, shift=shift,
                                        num_samples=run.num_samples, mc_seed=run.mc_seed,
                                        cache_dir=cache_dir)
    result = evaluate_sequence(seq, preds, gt, surface, config)
    if not per_sequence:
      path = os.path.join(out_dir, f"mesh_{seq.name}_shift{shift:g}.png")
      _figure_meshes(path, result["meshes"], surface, colors, config)
      files.append(path)
    del result["meshes"]
    per_sequence.append(result)
    names.append({"sequence": seq.name, "layout_seed": seed, "shift": shift,
                  "geometry": result["geometry"]})
  summary = summarize(per_sequence, config)
  shifts = sorted({n["shift"] for n in names})
  if len(shifts) > 1:   # the same per shift, as the study reports
    summary["by_shift"] = {
        f"{shift:g}": summarize([r for r, n in zip(per_sequence, names) if n["shift"] == shift],
                                config) for shift in shifts}
  table = format_tables(summary, config)
  path = os.path.join(out_dir, "mesh_study.png")
  _figure_bars(path, summary)
  files.append(path)
  record = {"config": {"run": dataclasses.asdict(run),
                       "geometry": dataclasses.asdict(config.geometry),
                       "learned_source": config.learned_source,
                       "fitted": [[tag, family] for tag, family, _ in config.fitted],
                       "surface_spacing": config.surface_spacing, "upsample": config.upsample,
                       "num_resamples": config.num_resamples,
                       "confidence": config.confidence},
            "model": front_end.model_id, "summary": summary, "sequences": names}
  files += _write_report(out_dir, record, config, table, (
      f"{len(per_sequence)} sequences (layout seeds {list(run.layout_seeds)}, shifts "
      f"{list(run.shifts)}, {run.num_frames} frames at {run.height}×{run.width}, M = "
      f"{run.num_samples})"))
  return {"summary": summary, "table": table, "files": files, "sequences": names,
          "timing": {"total_s": time.perf_counter() - start}}


def _write_report(out_dir: str, record: dict, config: MeshStudyConfig, table: str,
                  what: str) -> list:
  """Writes `mesh_study.json` (the record) and `mesh_study.md` (what ran, then the tables)."""
  path_json = os.path.join(out_dir, "mesh_study.json")
  with open(path_json, "w", encoding="utf-8") as f:
    json.dump(record, f, indent=1, default=float)
  path_md = os.path.join(out_dir, "mesh_study.md")
  with open(path_md, "w", encoding="utf-8") as f:
    f.write(f"# Mesh study\n\n{what}; geometry layer {config.geometry.voxel_size:g} m, τ = "
            f"{config.geometry.truncation_voxels:g} voxels.\n\n{table}\n")
  return [path_json, path_md]


def true_surface(item, config: MeshStudyConfig, label_space: Optional[str] = None) -> dict:
  """A loaded sequence's true surface: the embedded world's primitives where its cameras see
  them, or a ScanNet folder's labelled GT mesh (`surfaces.mesh_surface`)."""
  spec = item.spec
  if spec.is_embedded:
    return surfaces.sequence_surface(spec.env, spec.layout_seed, spec.shift, item.sequence,
                                     domain=spec.domain, spacing=config.surface_spacing,
                                     upsample=config.upsample)
  path = surfaces.labelled_mesh_path(spec.path) if os.path.isdir(spec.path) else None
  if path is None:
    raise ValueError(f"{spec}: no labelled GT mesh (*{surfaces.MESH_SUFFIX}) to score meshes "
                     "against; the mesh study needs one per sequence")
  return surfaces.mesh_surface(path, item.sequence, label_space=label_space or "scannet12",
                               spacing=config.surface_spacing)


def run_mesh_study_data(config: MeshStudyConfig, out_dir: str, specs, options, *,
                        front_end=None, checkpoint: Optional[str] = None) -> dict:
  """The mesh study on a researcher's sequences (`--data`): each sequence's predictions and GT
  (`lab.sequences.load`), its true surface (`true_surface`), every rule's mesh against it.

  Returns:
    dict with `summary`, `table`, `files`, `sequences` and `timing`.
  """
  from jaxfusion.lab import sequences   # pylint: disable=import-outside-toplevel
  start = time.perf_counter()
  os.makedirs(out_dir, exist_ok=True)
  options = dataclasses.replace(options, voxel_size=config.run.voxel_size,
                                cache_dir=options.cache_dir or os.path.join(out_dir, "cache"))
  if options.predictions is None and front_end is None:
    front_end = frontend.FrontEnd(checkpoint, class_names=None)
  per_sequence, names, files, classes = [], [], [], None
  for spec in tqdm(list(specs), desc="sequences"):
    item = sequences.load(spec, options, front_end=front_end)
    if classes is None:
      classes = item.class_names
      k = flags.fitted_for_other("learned", config.learned or {}, len(classes))
      if config.learned is not None and k is not None:
        print(f"note: the learned rule is left out: fitted for {k} classes, the data has "
              f"{len(classes)}")
        config = dataclasses.replace(config, learned=None)
      config.validate()
    elif item.class_names != classes:
      raise ValueError(f"{item.name}: its classes are not the first sequence's; one study, one "
                       "label space")
    if item.predictions["var"] is None:
      raise ValueError(f"{item.name}: the predictions hold no 'var'; the robust rules need it")
    surface = true_surface(item, config, options.label_space)
    result = evaluate_sequence(item.sequence, item.predictions, item.gt, surface, config,
                               ignore_label=datasets.IGNORE_LABEL)
    if not per_sequence:
      path = os.path.join(out_dir, f"mesh_{item.name}.png")
      _figure_meshes(path, result["meshes"], surface, datasets.palette(classes), config)
      files.append(path)
    del result["meshes"]
    per_sequence.append(result)
    names.append({"sequence": item.name, "spec": str(item.spec), "source": item.source,
                  "geometry": result["geometry"]})
  summary = summarize(per_sequence, config)
  table = format_tables(summary, config)
  path = os.path.join(out_dir, "mesh_study.png")
  _figure_bars(path, summary)
  files.append(path)
  record = {"config": {"data": [str(s) for s in specs], "run": dataclasses.asdict(config.run),
                       "geometry": dataclasses.asdict(config.geometry),
                       "learned_source": config.learned_source,
                       "fitted": [[tag, family] for tag, family, _ in config.fitted],
                       "surface_spacing": config.surface_spacing,
                       "num_resamples": config.num_resamples, "confidence": config.confidence},
            "classes": list(classes), "summary": summary, "sequences": names}
  files += _write_report(out_dir, record, config, table, (
      f"{len(per_sequence)} sequences of your data ({', '.join(str(s) for s in specs)})"))
  return {"summary": summary, "table": table, "files": files, "sequences": names,
          "timing": {"total_s": time.perf_counter() - start}}


def add_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `jaxfusion mesh-study`."""
  p = subparsers.add_parser(
      "mesh-study", help="the maps' meshes against the embedded world's true surface: "
                         "geometry (Chamfer, F-score) and mesh mIoU per rule")
  p.add_argument("--quick", action="store_true",
                 help="1 seed × office × 1 trajectory × shifts 0 and 1, 12 frames at 60×80")
  p.add_argument("--out", default="outputs/mesh_study", help="output folder")
  flags.add_study_run(p, seeds_help=" (default the study's: 1 2 3)")
  p.add_argument("--variant", action="append", default=[], metavar="TAG=PARAMS_JSON",
                 help="one more fitted row (repeatable): a params.json of `jaxfusion "
                      "learn-rule` (GLFS, a learned rule or a member of the rule family)")
  flags.add_data(p)
  p.set_defaults(func=main)
  return p


def fitted_rows(specs) -> tuple:
  """`((tag, family, params), …)` of `--variant TAG=PARAMS_JSON` flags (any fitted family)."""
  out = []
  for spec in specs or []:
    tag, sep, path = spec.partition("=")
    if not sep or not tag or not path:
      raise ValueError(f"--variant takes TAG=PARAMS_JSON; got {spec!r}")
    family, params = learn.load_rule(path)
    out.append((tag, family, params))
  tags = [t for t, _, _ in out]
  if len(set(tags)) != len(tags):
    raise ValueError(f"--variant tags must differ; got {tags}")
  return tuple(out)


def main(args: argparse.Namespace) -> int:
  """Runs `jaxfusion mesh-study` from parsed arguments and prints the tables."""
  flags.check_at_least(args)
  learned, source = flags.learned_rule(args)
  config = MeshStudyConfig.of(
      args.quick, layout_seeds=flags.as_tuple(args.layout_seeds),
      shifts=flags.as_tuple(args.shifts), envs=flags.as_tuple(args.envs),
      trajectories=flags.as_tuple(args.trajectories), num_frames=args.frames,
      height=args.height, width=args.width, num_samples=args.num_samples, beta=args.beta,
      aggregate=args.aggregate, mc_seed=args.mc_seed, learned=learned, learned_source=source,
      num_resamples=args.resamples, fitted=fitted_rows(args.variant))
  data = flags.data_sets(args, "data")["--data"]
  if data is not None:
    options = flags.run_data_options(args, config.run)
    out = run_mesh_study_data(config, args.out, data, options, checkpoint=args.checkpoint)
  else:
    out = run_mesh_study(config, args.out, cache_dir=args.cache, checkpoint=args.checkpoint)
  print(out["table"])
  print(f"wrote {len(out['files'])} files under {args.out}/ in "
        f"{out['timing']['total_s']:.0f} s")
  return 0
