"""`jaxfusion demo`: the paper's experiment on the embedded world.

For each environment × trajectory (one layout seed, one shift), the front end runs once (MC
dropout for the robust rules, dropout off for the baselines) and is cached, the sequence is
fused with all six rules, and each map is scored against GT voxel labels; confusion matrices
are summed over trajectories, then IoU is computed — Tables I/II's layout. It writes the tables
(Markdown, CSV, JSON), a PLY and an `.npz` of every map, the per-class IoU bars, the Fig. 5-style
map views and the Fig. 2 outlier example.
"""

import argparse
import dataclasses
import os
from typing import Optional, Sequence

import numpy as np
from tqdm.auto import tqdm

import jaxfusion as jf
from jaxfusion import datasets
from jaxfusion import io
from jaxfusion import metrics
from jaxfusion.mapper import Mapper
from jaxfusion.lab import config as config_lib
from jaxfusion.lab import figures
from jaxfusion.lab import flags
from jaxfusion.lab import frontend
from jaxfusion.lab import reports

# The demo's geometry layer: 5 cm voxels, τ = 4 voxels, constant weights (the table grows).
GEOMETRY = jf.tsdf.TSDFConfig()


def fuse_with_rule(sequence, predictions: dict, rule, config: config_lib.RunConfig, *,
                   geometry=None):
  """Fuses a whole sequence with one rule; returns the final MapState.

  The robust rules (and the learned one) read the MC moments (`mean`, `var`), the baselines
  the dropout-off pass (`det`). The map starts at `config.capacity` and grows rather than
  drop a voxel (`Mapper`).
  `geometry` (a `tsdf.TSDFConfig`) fuses a geometry layer in the same calls.
  """
  mapper = Mapper(rule, num_classes=predictions["mean"].shape[-1],
                  voxel_size=config.voxel_size, capacity=config.capacity, geometry=geometry)
  moments = config_lib.uses_moments(rule.name)
  frames = jf.Frame(np.asarray(sequence.depth, np.float32),
                    np.asarray(sequence.T_world_cam, np.float32),
                    predictions["mean"] if moments else predictions["det"],
                    predictions["var"] if moments else None)
  return mapper.fuse_sequence(frames, sequence.camera)


def format_table(results: dict, class_names: Sequence[str]) -> str:
  """Markdown table in the paper's layout: rows = methods, columns = per-class IoU, mIoU, Acc."""
  header = ["Method"] + [c.capitalize() if c != "tv" else "TV" for c in class_names] + [
      "mIoU", "Acc."]
  lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
  for name, r in results.items():
    cells = ["–" if np.isnan(v) else f"{100 * v:.1f}" for v in r["iou"]]
    lines.append(f"| {name} | " + " | ".join(cells) +
                 f" | {100 * r['miou']:.1f} | {100 * r['accuracy']:.1f} |")
  return "\n".join(lines)


def _summarize(confusions: dict) -> dict:
  return {name: {"iou": metrics.iou_from_confusion(cm), "miou": metrics.mean_iou(cm),
                 "accuracy": metrics.accuracy(cm), "confusion": cm}
          for name, cm in confusions.items()}


def run_demo(config: config_lib.RunConfig, out_dir: str, *, cache_dir: Optional[str] = None,
             checkpoint: Optional[str] = None, front_end=None) -> dict:
  """Runs the demo and writes the tables (Markdown, CSV, JSON), maps and figures.

  Args:
    config: the run (one layout seed, one shift; validated here).
    out_dir: output folder.
    cache_dir: front-end cache folder (default `OUT/cache`).
    checkpoint: network weights (default: the shipped ones); ignored when `front_end` is given.
    front_end: any front end (`frontend.FrontEnd` protocol) instead of a checkpoint.

  Returns:
    dict with `table` (Markdown), `results` (per scope → per method), `files` (what was
    written), `unmatched` (per sequence: voxels only in the map / only in GT).
  """
  config.validate()
  if len(config.layout_seeds) != 1 or len(config.shifts) != 1:
    raise ValueError("the demo runs one layout seed at one shift; `jaxfusion study` runs grids")
  os.makedirs(out_dir, exist_ok=True)
  cache_dir = cache_dir or os.path.join(out_dir, "cache")
  front_end = front_end if front_end is not None else frontend.FrontEnd(checkpoint)
  class_names = list(datasets.CLASS_NAMES)
  colors = np.asarray(datasets.CLASS_COLORS, np.uint8)
  k = len(class_names)
  rules = {name: config.make_rule(name) for name in config.rules}
  display = {name: jf.rules.display_name(rule) for name, rule in rules.items()}
  confusions = {"all": {display[n]: np.zeros((k, k), np.int64) for n in rules}}
  unmatched, files = {}, []
  for (seed, env, traj), shift in tqdm(config.grid, desc="sequences"):
    seq = datasets.load_spec(datasets.SequenceSpec("synthetic", env, traj, config.domain),
                             num_frames=config.num_frames, height=config.height,
                             width=config.width, layout_seed=seed, shift=shift)
    gt = datasets.gt_voxel_labels(seq, voxel_size=config.voxel_size, capacity=config.capacity)
    preds = frontend.cached_predictions(front_end, seq, layout_seed=seed, shift=shift,
                                        num_samples=config.num_samples,
                                        mc_seed=config.mc_seed, cache_dir=cache_dir)
    confusions.setdefault(env, {display[n]: np.zeros((k, k), np.int64) for n in rules})
    views = {"Ground truth": gt}
    first = traj == config.trajectories[0]
    geometry = None   # the sequence's geometry layer: fused once, with the first rule
    meshes = {}
    for name, rule in rules.items():
      state = fuse_with_rule(seq, preds, rule, config,
                             geometry=GEOMETRY if geometry is None else None)
      geometry = state.geometry if geometry is None else geometry
      state = state.replace(geometry=geometry)
      voxels = jf.read_map(state)
      ev = metrics.evaluate_map(voxels, gt, k)
      confusions[env][display[name]] += ev["confusion"]
      confusions["all"][display[name]] += ev["confusion"]
      unmatched[f"{seq.name}/{name}"] = {"map_only": ev["map_only"], "gt_only": ev["gt_only"],
                                         "matched": ev["matched"]}
      stem = os.path.join(out_dir, "maps", f"{seq.name}_{name}")
      io.save_map(stem + ".npz", state, rule, class_names=class_names,
                  extra={"sequence": seq.name, "model": front_end.model_id,
                         "config": dataclasses.asdict(config)},
                  poses=seq.T_world_cam, camera=seq.camera, image_size=seq.image_size)
      io.export_ply(stem + ".ply", voxels, voxel_size=config.voxel_size, colors=colors,
                    mode="cubes" if first else "points")
      surface = jf.extract_mesh(state)
      io.save_mesh(stem + "_mesh.ply", surface, colors=colors, num_classes=k)
      files += [stem + ".npz", stem + ".ply", stem + "_mesh.ply"]
      views[display[name]] = voxels
      meshes[display[name]] = surface
    gt_npz = os.path.join(out_dir, "maps", f"{seq.name}_gt.npz")   # for `jaxfusion view`
    io.atomic_write(gt_npz, lambda tmp, gt=gt: _save_npz(tmp, gt))
    files.append(gt_npz)
    gt_path = os.path.join(out_dir, "maps", f"{seq.name}_gt.ply")
    io.export_ply(gt_path, gt, voxel_size=config.voxel_size, colors=colors,
                  mode="cubes" if first else "points")
    files.append(gt_path)
    if first:
      shown = {t: v for t, v in views.items() if t in ("Ground truth", "Bayesian", "D+R")}
      path = os.path.join(out_dir, f"maps_{seq.name}.png")
      figures.map_views(path, shown, voxel_size=config.voxel_size, colors=colors)
      files.append(path)
      path = os.path.join(out_dir, f"mesh_{seq.name}.png")
      figures.mesh_views(path, _mesh_panels(meshes, gt, colors, config.voxel_size))
      files.append(path)

  if len(config.envs) == 1:   # the per-environment table would repeat "all"
    confusions = {"all": confusions["all"]}
  results = {scope: _summarize(cms) for scope, cms in confusions.items()}
  table = "\n\n".join(f"**{scope}** ({_scope_note(scope, config)})\n\n"
                      + format_table(res, class_names) for scope, res in results.items())
  files += _write_tables(out_dir, results, class_names, table, config, unmatched)
  path = os.path.join(out_dir, "iou_bars.png")
  figures.iou_bars(path, {m: r["iou"] for m, r in results["all"].items()}, class_names, colors)
  files.append(path)
  path = os.path.join(out_dir, "outlier.png")
  figures.outlier_figure(path)
  files.append(path)
  return {"table": table, "results": results, "files": files, "unmatched": unmatched}


def _mesh_panels(meshes: dict, gt: dict, colors: np.ndarray, voxel_size: float) -> dict:
  """The demo's mesh figure: the geometry layer's mesh coloured by the GT label of each face's
  semantic voxel (grey where GT has none), then by Bayes's and D+R's face labels."""
  grey = np.array(io.UNLABELLED_RGB, np.uint8)
  palette = lambda labels: np.where((labels >= 0)[:, None], colors[np.maximum(labels, 0)], grey)
  panels = {}
  some = next(iter(meshes.values()))
  centroids = some.vertices[some.faces].mean(axis=1) if some.num_faces else np.zeros((0, 3))
  voxel = np.floor(centroids / voxel_size).astype(np.int64)
  lookup = {tuple(c): int(l) for c, l in zip(np.asarray(gt["coords"]), np.asarray(gt["labels"]))}
  gt_labels = np.array([lookup.get(tuple(c), -1) for c in voxel], np.int64)
  panels["Ground truth"] = (some.vertices, some.faces, palette(gt_labels))
  for title in ("Bayesian", "D+R"):
    if title in meshes:
      m = meshes[title]
      panels[title] = (m.vertices, m.faces, palette(m.face_labels))
  return panels


def _save_npz(path, arrays):
  with open(path, "wb") as f:
    np.savez(f, **arrays)


def _scope_note(scope, config):
  trajs = len(config.trajectories)
  envs = len(config.envs) if scope == "all" else 1
  return (f"{envs * trajs} sequence(s), {config.num_frames} frames at {config.height}×"
          f"{config.width}, M = {config.num_samples}, β = {config.beta}, "
          f"{config.voxel_size} m voxels, pixel aggregation: {config.aggregate}")


def _write_tables(out_dir, results, class_names, table, config, unmatched):
  paths = [os.path.join(out_dir, n) for n in ("results.md", "results.csv", "results.json")]
  reports.write_text(paths[0], table + "\n")
  reports.write_csv(paths[1], ([scope, method] + [f"{v:.4f}" for v in r["iou"]] +
                               [f"{r['miou']:.4f}", f"{r['accuracy']:.4f}"]
                               for scope, res in results.items() for method, r in res.items()),
                    header=["scope", "method"] + list(class_names) + ["mIoU", "Acc"])
  payload = {
      "config": dataclasses.asdict(config),
      "class_names": list(class_names),
      "results": {scope: {m: {"iou": [None if np.isnan(v) else float(v) for v in r["iou"]],
                              "miou": r["miou"], "accuracy": r["accuracy"],
                              "confusion": r["confusion"].tolist()}
                          for m, r in res.items()} for scope, res in results.items()},
      "unmatched": unmatched,
  }
  reports.write_json(paths[2], payload)
  return paths


def add_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `jaxfusion demo` and `jaxfusion figure`."""
  p = subparsers.add_parser("demo", help="the paper's experiment on the embedded world, end to end")
  p.add_argument("--quick", action="store_true", help="one short sequence (~1 min on 2 cores)")
  p.add_argument("--out", default="outputs/demo", help="output folder")
  flags.add_cache(p, default=None)
  flags.add_checkpoint(p)
  flags.add_fusion(p, voxels=False)
  flags.add_grid(p, envs=None, trajectories=None)
  flags.add_sizes(p, frames=None, height=None, width=None)
  flags.add_layout_seeds(p, default=[config_lib.RunConfig.layout_seeds[0]],
                         help_suffix=" (one; default 0)")
  flags.add_mc_seed(p)
  p.set_defaults(func=demo_command)

  fig = subparsers.add_parser("figure", help="the paper's Fig. 2 outlier example as a PNG")
  fig.add_argument("--out", default="outputs/outlier.png")
  fig.set_defaults(func=figure_command)
  return p


def figure_command(args: argparse.Namespace) -> int:
  """Runs `jaxfusion figure`: the outlier example (the paper's Fig. 2) as a PNG."""
  ex = figures.outlier_figure(args.out)
  print(f"wrote {args.out}: Bayesian posterior after the outlier "
        f"{np.round(ex['posterior']['Bayesian'], 3)}, D+R {np.round(ex['posterior']['D+R'], 3)}")
  return 0


def main(args: argparse.Namespace) -> int:
  """Runs the parsed command (`demo` or `figure`)."""
  return args.func(args)


def demo_command(args: argparse.Namespace) -> int:
  """Runs `jaxfusion demo` from parsed arguments and prints the table."""
  flags.check_at_least(args)
  config = config_lib.demo_config(
      args.quick, beta=args.beta, aggregate=args.aggregate, envs=flags.as_tuple(args.envs),
      trajectories=flags.as_tuple(args.trajectories), num_frames=args.frames,
      height=args.height, width=args.width, num_samples=args.num_samples,
      layout_seeds=(flags.one_layout_seed(args),), mc_seed=args.mc_seed)
  out = run_demo(config, args.out, cache_dir=args.cache, checkpoint=args.checkpoint)
  print(out["table"])
  print(f"\nwrote {len(out['files'])} files under {args.out}/ (results.md/.csv/.json, "
        "maps/*.ply and *.npz, iou_bars.png, maps_*.png, outlier.png)")
  return 0
