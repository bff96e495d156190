"""The `jaxfusion` command: demo, run, eval, export, list, render, figure, view, sweep, tune-beta.

Errors a user can fix (a wrong --data spec, an unreadable folder, an unknown rule, a mismatched
checkpoint or cache) are printed as one line and exit with status 2, without a traceback.
"""

import argparse
import os
import sys

import numpy as np
from tqdm.auto import tqdm


def parse_data_spec(spec: str):
  """`scannet:PATH`, `tum:PATH` or `synthetic:ENV/TRAJ[/DOMAIN]` → (kind, value)."""
  kind, sep, value = spec.partition(":")
  if not sep or kind not in ("scannet", "tum", "synthetic") or not value:
    raise ValueError(f"--data must be scannet:PATH, tum:PATH or synthetic:ENV/TRAJ "
                     f"(e.g. synthetic:office/0); got {spec!r}")
  if kind == "synthetic":
    parts = value.split("/")
    if len(parts) not in (2, 3) or parts[0] not in ("office", "house") or parts[1] not in (
        "0", "1", "2") or (len(parts) == 3 and parts[2] not in ("train", "test")):
      raise ValueError(f"synthetic data is ENV/TRAJ[/DOMAIN] with ENV office|house, TRAJ 0|1|2, "
                       f"DOMAIN train|test; got {value!r}")
    return kind, (parts[0], int(parts[1]), parts[2] if len(parts) == 3 else "test")
  if not os.path.isdir(value):
    raise FileNotFoundError(f"--data {kind}: no such folder {value!r}")
  return kind, value


def load_data(spec: str, args):
  from jaxfusion import datasets
  kind, value = parse_data_spec(spec)
  if kind == "synthetic":
    env, traj, domain = value
    return datasets.make_sequence(env, traj, domain=domain, num_frames=args.frames,
                                  height=args.height, width=args.width)
  loader = datasets.load_scannet if kind == "scannet" else datasets.load_tum
  seq = loader(value, stride=args.stride, max_frames=args.frames, skip_bad=True)
  if len(seq) == 0:
    raise ValueError(f"--data {spec}: no readable frames")
  return seq


def _predictions(seq, args):
  """Per-frame (probs, var) from precomputed files or the shipped network."""
  import jax
  import jaxfusion as jf
  if args.predictions:
    source = jf.sources.precomputed_source(args.predictions)
    if len(source) != len(seq):
      raise ValueError(f"--predictions has {len(source)} frames but the data has {len(seq)}")
    for t in range(len(seq)):
      pred = source.predict(None, None, index=t)
      yield np.asarray(pred.probs), None if pred.var is None else np.asarray(pred.var)
    return
  import jaxfusion_models as models
  model = models.load(args.checkpoint or models.PRETRAINED_PATH, class_names=None)
  if len(model.class_names) != len(seq.class_names) and seq.labels is not None:
    tqdm.write(f"note: the network has {len(model.class_names)} classes and the data "
               f"{len(seq.class_names)}; the map will not be scored")
  key = jax.random.PRNGKey(args.seed)
  for t in range(len(seq)):
    if args.num_samples > 1:
      samples = models.mc_samples(model.graphdef, model.params, jax.random.fold_in(key, t),
                                  seq.rgb[t], num_samples=args.num_samples)
      mean, var = jf.mc_moments(samples)
      yield np.asarray(mean), np.asarray(var)
    else:
      yield np.asarray(models.deterministic_probs(model.graphdef, model.params, seq.rgb[t])), None


def cmd_run(args):
  import jaxfusion as jf
  from jaxfusion import datasets, io, metrics
  rule = jf.rules.by_name(args.rule, **_rule_kwargs(args))
  if rule.requires_var and args.num_samples < 2 and not args.predictions:
    raise ValueError(f"rule {args.rule} needs epistemic variance: use --num-samples ≥ 2")
  seq = load_data(args.data, args)
  state, num_classes = None, None
  for t, (probs, var) in enumerate(tqdm(_predictions(seq, args), total=len(seq), desc="fusing")):
    if state is None:
      num_classes = probs.shape[-1]
      state = jf.init_map(capacity=args.capacity, num_classes=num_classes,
                          voxel_size=args.voxel_size, rule=rule)
    state = jf.fuse_frame(state, jf.Frame(seq.depth[t], seq.T_world_cam[t], probs, var),
                          seq.camera, rule)
  voxels = jf.read_map(state)
  os.makedirs(args.out, exist_ok=True)
  stem = os.path.join(args.out, f"{seq.name}_{rule.name}")
  names = seq.class_names if len(seq.class_names) == num_classes else None
  io.save_map(stem + ".npz", state, rule, class_names=names,
              extra={"data": args.data, "sequence": seq.name}, poses=seq.T_world_cam,
              camera=seq.camera, image_size=seq.image_size)
  colors = _colors(num_classes)
  io.export_ply(stem + ".ply", voxels, voxel_size=args.voxel_size, colors=colors)
  print(f"map: {len(voxels['coords'])} voxels → {stem}.npz, {stem}.ply")
  if seq.labels is not None and names is not None:
    gt = datasets.gt_voxel_labels(seq, voxel_size=args.voxel_size, capacity=args.capacity)
    gt_path = stem + "_gt.npz"
    io.atomic_write(gt_path, lambda tmp: np.savez(open(tmp, "wb"), **gt))
    ev = metrics.evaluate_map(voxels, gt, num_classes, ignore_label=datasets.IGNORE_LABEL)
    print(_score_line(ev, names))
    print(f"GT voxel labels → {gt_path}")


def _score_line(ev, names):
  ious = ", ".join(f"{n} {100 * v:.1f}" for n, v in zip(names, ev["iou"]) if not np.isnan(v))
  return (f"mIoU {100 * ev['miou']:.1f}  Acc {100 * ev['accuracy']:.1f}  ({ev['matched']} "
          f"voxels scored, {ev['map_only']} only in the map, {ev['gt_only']} only in GT)\n"
          f"IoU: {ious}")


def _colors(num_classes):
  from jaxfusion import datasets, io
  if num_classes == len(datasets.CLASS_COLORS):
    return np.asarray(datasets.CLASS_COLORS, np.uint8)
  if num_classes == len(datasets.SCANNET_COLORS):
    return np.asarray(datasets.SCANNET_COLORS, np.uint8)
  return io.default_palette(num_classes)


def _rule_kwargs(args):
  kwargs = {"aggregate": args.aggregate}
  if args.rule.lower() in ("robust_r", "robust_d", "robust_dr", "r", "d", "d+r"):
    kwargs["beta"] = args.beta
  return kwargs


def cmd_eval(args):
  from jaxfusion import datasets, io, metrics
  import jaxfusion as jf
  state, rule, meta = io.load_map(args.map)
  if not os.path.exists(args.gt):
    raise FileNotFoundError(f"--gt: no such file {args.gt!r}")
  with np.load(args.gt) as f:
    if "coords" not in f or "labels" not in f:
      raise ValueError(f"{args.gt} must hold 'coords' and 'labels' (as written by "
                       "`jaxfusion run`)")
    gt = {"coords": f["coords"], "labels": f["labels"]}
  ev = metrics.evaluate_map(jf.read_map(state), gt, state.num_classes,
                            ignore_label=datasets.IGNORE_LABEL)
  names = meta["class_names"] or [str(i) for i in range(state.num_classes)]
  print(f"{jf.rules.display_name(rule)}: " + _score_line(ev, names))


def cmd_export(args):
  from jaxfusion import io
  import jaxfusion as jf
  state, _, meta = io.load_map(args.map)
  voxels = jf.read_map(state)
  io.export_ply(args.out, voxels, voxel_size=float(state.voxel_size),
                colors=_colors(state.num_classes), mode=args.mode)
  print(f"{len(voxels['coords'])} voxels → {args.out}")


def cmd_demo(args):
  from jaxfusion.lab import demo as experiments
  overrides = {"beta": args.beta, "aggregate": args.aggregate}
  for name in ("envs", "trajectories"):
    if getattr(args, name):
      overrides[name] = tuple(getattr(args, name))
  for name, field in (("frames", "num_frames"), ("height", "height"), ("width", "width"),
                      ("num_samples", "num_samples")):
    if getattr(args, name) is not None:
      if getattr(args, name) < 1:
        raise ValueError(f"--{name.replace('_', '-')} must be at least 1")
      overrides[field] = getattr(args, name)
  config = (experiments.ExperimentConfig.quick(**overrides) if args.quick
            else experiments.ExperimentConfig(**overrides))
  out = experiments.run_experiment(config, args.out, cache_dir=args.cache,
                                   checkpoint=args.checkpoint)
  print(out["table"])
  print(f"\nwrote {len(out['files'])} files under {args.out}/ (results.md/.csv/.json, "
        "maps/*.ply and *.npz, iou_bars.png, maps_*.png, outlier.png)")


def cmd_figure(args):
  from jaxfusion.lab import figures
  ex = figures.outlier_figure(args.out)
  print(f"wrote {args.out}: Bayesian posterior after the outlier "
        f"{np.round(ex['posterior']['Bayesian'], 3)}, D+R {np.round(ex['posterior']['D+R'], 3)}")


def cmd_datasets(args, extra):
  from jaxfusion.lab import data
  return data.main([args.command] + extra)


def build_parser():
  p = argparse.ArgumentParser(prog="jaxfusion", description=__doc__.splitlines()[0])
  sub = p.add_subparsers(dest="command", required=True)

  demo = sub.add_parser("demo", help="the paper's experiment on the embedded world, end to end")
  demo.add_argument("--quick", action="store_true", help="one short sequence (~2 min on 2 cores)")
  demo.add_argument("--out", default="outputs/demo", help="output folder")
  demo.add_argument("--cache", default=None, help="front-end cache folder (default OUT/cache)")
  demo.add_argument("--checkpoint", default=None, help="network weights (default: shipped)")
  demo.add_argument("--beta", type=float, default=0.3)
  demo.add_argument("--aggregate", choices=("sum", "mean"), default="sum")
  demo.add_argument("--envs", nargs="+", choices=("office", "house"), default=None)
  demo.add_argument("--trajectories", nargs="+", type=int, choices=(0, 1, 2), default=None)
  demo.add_argument("--frames", type=int, default=None, help="frames per trajectory")
  demo.add_argument("--height", type=int, default=None)
  demo.add_argument("--width", type=int, default=None)
  demo.add_argument("--num-samples", type=int, default=None, help="MC dropout samples M")
  demo.set_defaults(func=cmd_demo)

  run = sub.add_parser("run", help="fuse one sequence of your data with one rule")
  run.add_argument("--data", required=True, help="scannet:PATH | tum:PATH | synthetic:ENV/TRAJ")
  run.add_argument("--rule", default="robust_dr", help="sum_probs, sum_labels, bayes, R, D, D+R")
  run.add_argument("--beta", type=float, default=0.3)
  run.add_argument("--aggregate", choices=("sum", "mean"), default="sum")
  run.add_argument("--predictions", default=None,
                   help="folder of precomputed .npz predictions (one per frame) instead of the "
                        "shipped network")
  run.add_argument("--checkpoint", default=None)
  run.add_argument("--num-samples", type=int, default=32, help="MC dropout samples (1 = off)")
  run.add_argument("--frames", type=int, default=40, help="frames (synthetic) / max frames")
  run.add_argument("--stride", type=int, default=1, help="keep every N-th frame (real data)")
  run.add_argument("--height", type=int, default=120)
  run.add_argument("--width", type=int, default=160)
  run.add_argument("--voxel-size", type=float, default=0.1)
  run.add_argument("--capacity", type=int, default=2**18)
  run.add_argument("--seed", type=int, default=0)
  run.add_argument("--out", default="outputs/run")
  run.set_defaults(func=cmd_run)

  ev = sub.add_parser("eval", help="score a saved map against GT voxel labels")
  ev.add_argument("--map", required=True, help="map .npz from `jaxfusion run` / `demo`")
  ev.add_argument("--gt", required=True, help="GT voxel labels .npz (coords, labels)")
  ev.set_defaults(func=cmd_eval)

  ex = sub.add_parser("export", help="export a saved map as a class-coloured PLY")
  ex.add_argument("--map", required=True)
  ex.add_argument("--out", required=True)
  ex.add_argument("--mode", choices=("cubes", "points"), default="cubes")
  ex.set_defaults(func=cmd_export)

  fig = sub.add_parser("figure", help="the paper's Fig. 2 outlier example as a PNG")
  fig.add_argument("--out", default="outputs/outlier.png")
  fig.set_defaults(func=cmd_figure)

  for name, text in (("list", "list the embedded sequences"),
                     ("render", "render an embedded frame as RGB | depth | labels PNG "
                                "(see `python -m jaxfusion.datasets render --help`)")):
    sub.add_parser(name, help=text, add_help=False).set_defaults(func=None)

  from jaxfusion.lab.viewer import command as view_command   # imports viser only when it runs
  view_command.add_parser(sub)

  from jaxfusion.lab import study
  study.add_study_parser(sub)

  from jaxfusion.lab import tuning
  for builder in (tuning.add_sweep_parser, tuning.add_tune_beta_parser,
                  tuning.add_tune_compare_parser, tuning.add_tune_protocol_parser):
    builder(sub)
  from jaxfusion.lab import simulate
  simulate.add_simulate_sweep_parser(sub)
  return p


def main(argv=None) -> int:
  argv = list(sys.argv[1:] if argv is None else argv)
  parser = build_parser()
  if argv and argv[0] in ("list", "render"):
    args = argparse.Namespace(command=argv[0])
    return cmd_datasets(args, argv[1:]) or 0
  args = parser.parse_args(argv)
  try:
    import jaxfusion_models
    errors = (ValueError, FileNotFoundError, jaxfusion_models.CheckpointError)
  except ImportError:
    errors = (ValueError, FileNotFoundError)
  try:
    args.func(args)
  except errors as e:
    print(f"jaxfusion {args.command}: error: {e}", file=sys.stderr)
    return 2
  return 0


if __name__ == "__main__":
  sys.exit(main())
