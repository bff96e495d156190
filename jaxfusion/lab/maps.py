"""Commands on one map: `jaxfusion run` (fuse a sequence of your data with one rule), `eval`
(score a saved map against GT voxel labels) and `export` (a saved map as a PLY).

`run --free-space` makes the map with free-space clearing (docs/equations.md §10): voxels a
later frame shows as free are not read out, so the saved map, its PLY and its score are those of
the cleared map (the map file keeps the occupancy log-odds; its name ends in `_free`).
`run --true-poses` fuses a drifting sequence (`office:0:drift`) at its true poses
(`info["true_poses"]`) instead of the drifted ones it stores (its name ends in `_true_poses`).
"""

import argparse
import dataclasses
import os

import numpy as np
from tqdm.auto import tqdm

import jaxfusion as jf
from jaxfusion import datasets
from jaxfusion import io
from jaxfusion import metrics
from jaxfusion.lab import flags
from jaxfusion.lab import frontend

# Frames fused per `fuse_sequence` call by `run`: the network's outputs are streamed, so a long
# real sequence never has to fit in memory, and each chunk is one compiled scan.
RUN_CHUNK = 16


def _class_map(args):
  """The `--class-map` (a file, or the name of a shipped one), or None."""
  return flags.class_map(args)


def _index_names(names) -> bool:
  """Names that only number the classes ("0", "1", ...): a class map given by counts."""
  return tuple(names) == tuple(str(i) for i in range(len(names)))


def _check_source_classes(class_map, num_classes: int, what: str, names=None) -> None:
  if num_classes != class_map.num_source_classes:
    raise ValueError(f"--class-map maps {class_map.num_source_classes} source classes but "
                     f"{what} {num_classes} classes")
  if names is not None and not _index_names(class_map.source_classes) and (
      tuple(names) != tuple(class_map.source_classes)):
    raise ValueError(f"--class-map: its source classes {list(class_map.source_classes)} are "
                     f"not the network's {list(names)} (same classes, same order)")


def _predictions(seq, args, class_map=None):
  """Per-frame `(probs, var)` from precomputed files or a network (var None with M = 1),
  remapped by `class_map` (samples before their moments, where there are samples)."""
  import jax  # pylint: disable=import-outside-toplevel
  remap = jax.jit(jf.ClassMap.remap)
  remap_samples = jax.jit(jf.ClassMap.remap_samples)
  # mc_moments stays outside jit: its loop over M would unroll into an O(M) graph.
  moments = lambda cm, samples: jf.mc_moments(remap_samples(cm, samples))
  if args.predictions:
    source = jf.sources.precomputed_source(args.predictions)
    if len(source) != len(seq):
      raise ValueError(f"--predictions has {len(source)} frames but the data has {len(seq)}")
    for t in range(len(seq)):
      frame = source.read(t)                           # one read of the file
      what = f"--predictions {source.files[t]} has"
      if frame.samples is None:
        probs, var = frame.probs, frame.var
        if class_map is not None:
          _check_source_classes(class_map, probs.shape[-1], what)
          probs, var = remap(class_map, probs, var)
      elif class_map is None:
        probs, var = jf.mc_moments(frame.samples)
      else:                                            # remap the samples, then their moments
        _check_source_classes(class_map, frame.samples.shape[-1], what)
        probs, var = moments(class_map, frame.samples)
      yield np.asarray(probs), None if var is None else np.asarray(var)
    return
  net = frontend.FrontEnd(args.checkpoint, class_names=None)
  if class_map is not None:
    _check_source_classes(class_map, len(net.class_names), "the network has",
                          names=net.class_names)
  elif len(net.class_names) != len(seq.class_names) and seq.labels is not None:
    tqdm.write(f"note: the network has {len(net.class_names)} classes and the data "
               f"{len(seq.class_names)}; the map will not be scored")
  key = jax.random.PRNGKey(args.mc_seed)
  for t in range(len(seq)):
    if args.num_samples > 1:
      key_t = jax.random.fold_in(key, t)
      if class_map is None:
        yield net.mc(seq.rgb[t], num_samples=args.num_samples, key=key_t)
      else:
        samples = net.mc_samples(seq.rgb[t], num_samples=args.num_samples, key=key_t)
        yield tuple(np.asarray(a) for a in moments(class_map, samples))
    else:
      probs = net.deterministic(seq.rgb[t])
      yield (probs if class_map is None else np.asarray(remap(class_map, probs)[0])), None


def _chunks(seq, predictions, size, rgb: bool = False):
  """Stacks of up to `size` frames: `(t0, Frame with a leading time axis)`; with `rgb`, the
  colour images too (rules that read image context)."""
  buf = []
  for t, (probs, var) in enumerate(predictions):
    buf.append((t, probs, var))
    if len(buf) == size or t == len(seq) - 1:
      idx = [b[0] for b in buf]
      var_stack = None if buf[0][2] is None else np.stack([b[2] for b in buf])
      yield len(buf), jf.Frame(np.asarray(seq.depth[idx], np.float32),
                               np.asarray(seq.T_world_cam[idx], np.float32),
                               np.stack([b[1] for b in buf]), var_stack,
                               np.asarray(seq.rgb[idx], np.uint8) if rgb else None)
      buf = []


def _rule(args, num_classes=None):
  """`--rule`: any rule the study has (`flags.resolve_rule`)."""
  return flags.resolve_rule(args.rule, beta=args.beta, aggregate=args.aggregate,
                            num_classes=num_classes)[1]


def _at_true_poses(seq, data: str):
  """`--true-poses`: the sequence with its stored (drifted) poses replaced by
  `info["true_poses"]`; one line when it has none."""
  true_poses = seq.info.get("true_poses")
  if true_poses is None:
    raise ValueError(f"--true-poses: {data} has no true poses (only a drifting sequence "
                     "carries them, e.g. office:0:drift)")
  true_poses = np.asarray(true_poses, np.float32)
  if true_poses.shape != seq.T_world_cam.shape:
    raise ValueError(f"--true-poses: the true poses of {data} have shape {true_poses.shape}, "
                     f"its poses {seq.T_world_cam.shape}")
  return dataclasses.replace(seq, T_world_cam=true_poses)


def run_command(args: argparse.Namespace) -> int:
  """Runs `jaxfusion run`: fuses one sequence with one rule, saves and scores the map."""
  rule = _rule(args)
  if rule.requires_var and args.num_samples < 2 and not args.predictions:
    raise ValueError(f"rule {args.rule} needs epistemic variance: use --num-samples ≥ 2")
  try:
    spec = datasets.parse_spec(args.data)
  except ValueError as e:
    raise ValueError(f"--data: {e}") from None
  class_map = _class_map(args)
  seq = datasets.load_spec(spec, num_frames=args.frames, height=args.height, width=args.width,
                           layout_seed=flags.one_layout_seed(args), stride=args.stride,
                           label_space=args.label_space, label_tsv=args.label_tsv)
  if args.true_poses:
    seq = _at_true_poses(seq, args.data)
  mapper, num_classes = None, None
  with tqdm(total=len(seq), desc="fusing") as bar:
    for count, frames in _chunks(seq, _predictions(seq, args, class_map), RUN_CHUNK,
                                 rgb=bool(rule.context)):
      if mapper is None:
        num_classes = frames.probs.shape[-1]
        rule = _rule(args, num_classes)          # a fitted rule's K checked against the data
        mapper = jf.Mapper(rule, num_classes=num_classes, voxel_size=args.voxel_size,
                           capacity=args.capacity, geometry=flags.geometry_config(args),
                           free_space=bool(args.free_space))
      mapper.fuse_sequence(frames, seq.camera)
      bar.update(count)
  state = mapper.state
  for frames_done, old, new in mapper.growths:
    tqdm.write(f"the map grew from {old} to {new} slots after {frames_done} frames")
  voxels = jf.read_map(state)
  os.makedirs(args.out, exist_ok=True)
  suffix = ("_true_poses" if args.true_poses else "") + ("_free" if args.free_space else "")
  stem = os.path.join(args.out, f"{seq.name}_{rule.name}{suffix}")
  names = seq.class_names if len(seq.class_names) == num_classes else None
  scored = names is not None
  if class_map is not None and not _index_names(class_map.target_classes):
    names = class_map.target_classes     # the map's classes: its palette, its saved names
    scored = tuple(names) == tuple(seq.class_names)
    if seq.labels is not None and not scored:
      print(f"note: the class map's target classes are not the data's "
            f"{list(seq.class_names)}; the map is not scored")
  extra = {"data": args.data, "sequence": seq.name, "free_space": bool(args.free_space),
           "true_poses": bool(args.true_poses)}
  if class_map is not None:
    extra["class_map"] = str(args.class_map)
  io.save_map(stem + ".npz", state, rule, class_names=names, extra=extra,
              poses=seq.T_world_cam, camera=seq.camera, image_size=seq.image_size)
  io.export_ply(stem + ".ply", voxels, voxel_size=args.voxel_size,
                colors=datasets.palette(num_classes if names is None else names))
  cleared = ""
  if state.free_space is not None:
    cleared = f" ({jf.map_stats(state)['free']} stored voxels cleared as free space)"
  print(f"map: {len(voxels['coords'])} voxels{cleared} → {stem}.npz, {stem}.ply")
  if state.geometry is not None:
    surface = jf.extract_mesh(state)
    io.save_mesh(stem + "_mesh.ply", surface, colors=datasets.palette(
        num_classes if names is None else names), num_classes=num_classes)
    print(f"mesh: {surface.num_vertices} vertices, {surface.num_faces} triangles → "
          f"{stem}_mesh.ply")
    if state.free_space is not None:
      print("note: free space clears the semantic voxels, not the geometry layer: the mesh "
            "may keep surfaces of objects that have since moved away")
  if seq.labels is not None and scored:
    gt = datasets.gt_voxel_labels(seq, voxel_size=args.voxel_size)
    gt_path = stem + "_gt.npz"
    io.save_npz(gt_path, gt)
    ev = metrics.evaluate_map(voxels, gt, num_classes, ignore_label=datasets.IGNORE_LABEL)
    print(score_line(ev, names))
    print(f"GT voxel labels → {gt_path}")
  return 0


def score_line(ev: dict, names) -> str:
  """Two lines: map mIoU, accuracy and the voxel counts of `metrics.evaluate_map`, then the
  per-class IoU."""
  ious = ", ".join(f"{n} {100 * v:.1f}" for n, v in zip(names, ev["iou"]) if not np.isnan(v))
  return (f"mIoU {100 * ev['miou']:.1f}  Acc {100 * ev['accuracy']:.1f}  ({ev['matched']} "
          f"voxels scored, {ev['map_only']} only in the map, {ev['gt_only']} only in GT)\n"
          f"IoU: {ious}")


def eval_command(args: argparse.Namespace) -> int:
  """Runs `jaxfusion eval`: scores a saved map against GT voxel labels."""
  state, rule, meta = io.load_map(args.map)
  if not os.path.exists(args.gt):
    raise FileNotFoundError(f"--gt: no such file {args.gt!r}")
  what = "GT voxel-label file with 'coords' and 'labels' (as written by `jaxfusion run`)"
  f = io.read_npz(args.gt, what=what, required=("coords", "labels"))
  io.check_array(args.gt, what, "coords", f["coords"], (None, 3), f["coords"].dtype)
  io.check_array(args.gt, what, "labels", f["labels"], (len(f["coords"]),), f["labels"].dtype)
  if not (np.issubdtype(f["coords"].dtype, np.integer)
          and np.issubdtype(f["labels"].dtype, np.integer)):
    raise io.BadFileError(f"{args.gt} is not a {what} (coords and labels must be integers)")
  gt = {"coords": f["coords"], "labels": f["labels"]}
  ev = metrics.evaluate_map(jf.read_map(state), gt, state.num_classes,
                            ignore_label=datasets.IGNORE_LABEL)
  names = meta["class_names"] or [str(i) for i in range(state.num_classes)]
  print(f"{jf.rules.display_name(rule)}: " + score_line(ev, names))
  return 0


def export_command(args: argparse.Namespace) -> int:
  """Runs `jaxfusion export`: writes a saved map as a class-coloured PLY of its voxels
  (`--out`) and/or a mesh of its geometry layer (`--mesh`, PLY / OBJ / GLB)."""
  if args.out is None and args.mesh is None:
    raise ValueError("export: give --out (voxels as PLY) and/or --mesh (mesh as .ply/.obj/.glb)")
  state, _, meta = io.load_map(args.map)
  colors = datasets.palette(meta["class_names"] or state.num_classes)
  if args.out is not None:
    voxels = jf.read_map(state)
    io.export_ply(args.out, voxels, voxel_size=float(state.voxel_size), colors=colors,
                  mode=args.mode)
    print(f"{len(voxels['coords'])} voxels → {args.out}")
  if args.mesh is not None:
    if state.geometry is None:
      raise ValueError(f"export --mesh: {args.map} has no geometry layer (maps written by "
                       "`jaxfusion run` and `demo` have one)")
    surface = jf.extract_mesh(state, classes=args.classes, min_weight=args.min_weight)
    io.save_mesh(args.mesh, surface, color_by=args.color_by, colors=colors,
                 num_classes=state.num_classes)
    print(f"mesh: {surface.num_vertices} vertices, {surface.num_faces} triangles "
          f"(coloured by {args.color_by}) → {args.mesh}")
  return 0


def add_parser(subparsers) -> None:
  """Adds `run`, `eval` and `export`."""
  run = subparsers.add_parser("run", help="fuse one sequence of your data with one rule")
  run.add_argument("--data", required=True,
                   help="the sequence: ENV:TRAJECTORY (e.g. office:0), scannet:PATH, tum:PATH "
                        "or saved:PATH (also synthetic:ENV/TRAJECTORY)")
  run.add_argument("--rule", default="robust_dr", help=flags.RULE_NAMES_HELP)
  flags.add_fusion(run)
  run.add_argument("--predictions", default=None,
                   help="folder of precomputed .npz predictions (one per frame) instead of the "
                        "shipped network")
  flags.add_label_space(run)
  flags.add_checkpoint(run)
  run.add_argument("--num-samples", type=int, default=32, help="MC dropout samples (1 = off)")
  run.add_argument("--frames", type=int, default=40,
                   help="frames of an embedded sequence / the most frames read from a folder")
  run.add_argument("--stride", type=int, default=1, help="keep every N-th frame (folders)")
  run.add_argument("--height", type=int, default=120, help="image rows (embedded sequences)")
  run.add_argument("--width", type=int, default=160, help="image columns (embedded sequences)")
  run.add_argument("--capacity", type=int, default=2**16,
                   help="initial map capacity (a power of two); the map grows as needed")
  flags.add_geometry(run)
  run.add_argument("--free-space", action="store_true",
                   help="free-space clearing: voxels a later frame sees through are not read "
                        "out, a re-hit free voxel restarts (docs/equations.md §10)")
  run.add_argument("--true-poses", action="store_true",
                   help="fuse a drifting sequence (e.g. office:0:drift) at its true poses "
                        "instead of the drifted ones")
  flags.add_layout_seeds(run, default=[0], help_suffix=" (one; default 0)")
  flags.add_mc_seed(run, aliases=("--seed",))
  run.add_argument("--out", default="outputs/run")
  run.set_defaults(func=run_command)

  ev = subparsers.add_parser("eval", help="score a saved map against GT voxel labels")
  ev.add_argument("--map", required=True, help="map .npz from `jaxfusion run` / `demo`")
  ev.add_argument("--gt", required=True, help="GT voxel labels .npz (coords, labels)")
  ev.set_defaults(func=eval_command)

  ex = subparsers.add_parser("export", help="export a saved map: voxels as a class-coloured "
                                            "PLY, its surface as a mesh")
  ex.add_argument("--map", required=True)
  ex.add_argument("--out", default=None, help="voxels as a PLY (cubes or points)")
  ex.add_argument("--mode", choices=("cubes", "points"), default="cubes")
  ex.add_argument("--mesh", default=None, metavar="FILE",
                  help="the geometry layer's mesh: .ply, .obj or .glb")
  ex.add_argument("--color-by", choices=io.MESH_COLORINGS, default="class",
                  help="mesh vertex colours: class (the map's palette), confidence or entropy")
  ex.add_argument("--classes", type=int, nargs="+", default=None,
                  help="mesh only these classes (indices)")
  ex.add_argument("--min-weight", type=float, default=jf.mesh.DEFAULT_MIN_WEIGHT,
                  help="skip cubes with a corner of lower TSDF weight")
  ex.set_defaults(func=export_command)


def main(args: argparse.Namespace) -> int:
  """Runs the parsed command (`run`, `eval` or `export`)."""
  return args.func(args)
