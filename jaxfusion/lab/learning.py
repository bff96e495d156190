"""`jaxfusion learn-rule`: fit the learned fusion rule by gradient through fusion on calibration
layouts, with early stopping on other layouts, and write its parameters and a record.

The training layouts and the validation layouts are disjoint from each other and from every
layout the rules are judged on (the demo's seed 0, the study's 1–3, the tuning protocol's 1–3).
Sequences at several domain shifts go into one training batch. Outputs under `--out`:
`params.json` (what `rules.learned` takes; `jaxfusion.learn.load_params` reads it), `record.json`
(data, settings, steps, loss curves, time), `loss.png` and `weights.png` (the learned per-pixel weight over α and
the max probability, beside D's α/ᾱ).
"""

import argparse
import os
import time
from typing import Sequence

import numpy as np

from jaxfusion import context as context_lib
from jaxfusion import learn
from jaxfusion import rules
from jaxfusion import tune
from jaxfusion.lab import figures
from jaxfusion.lab import flags
from jaxfusion.lab import reports
from jaxfusion.lab import tuning

DEFAULT_OUT = "outputs/learned_rule"
TRAIN_SEEDS = (11, 12)
VALIDATION_SEEDS = (13,)
# Layout seeds some command judges rules on: a learned rule must never see them.
JUDGED_SEEDS = (0, 1, 2, 3)


def merge_batches(batches: Sequence[dict]) -> dict:
  """One batch of the sequences of several `tuning.load_sequence_batch` batches (equal T, H, W
  and camera), the GT padded to the longest."""
  frames = [b["frames"] for b in batches]
  shapes = {np.shape(f.depth)[1:] for f in frames}
  if len(shapes) != 1:
    raise ValueError(f"batches to merge must share T, H and W; got {sorted(shapes)}")
  cat = lambda xs: None if xs[0] is None else np.concatenate(xs)
  merged = type(frames[0])(*(cat([getattr(f, name) for f in frames])
                             for name in frames[0]._fields))
  coords, labels = tune.pad_ground_truth([{"coords": c, "labels": l} for b in batches
                                          for c, l in zip(b["coords"], b["labels"])])
  return {"names": [n for b in batches for n in b["names"]], "frames": merged,
          "mask": np.concatenate([b["mask"] for b in batches]), "camera": batches[0]["camera"],
          "coords": coords, "labels": labels,
          "capacity": max(b["capacity"] for b in batches),
          "num_classes": batches[0]["num_classes"], "source": batches[0]["source"]}


def add_parser(subparsers) -> None:
  """Adds `learn-rule`."""
  parser = subparsers.add_parser(
      "learn-rule", help="fit the learned fusion rule on calibration layouts (gradient through "
                         "fusion, early stopping on other layouts)",
      description="Fits rules.learned (docs/equations.md §3.9) by Adam on the cross-entropy of "
                  "the fused voxel posteriors against GT voxel labels, through the whole scan "
                  "of frames, on the training layout seeds at every --shifts value; stops when "
                  "the same loss (or, with --select miou, the map mIoU) on the validation seeds "
                  "has not improved for --patience evaluations; writes params.json, record.json, loss.png and weights.png.")
  parser.add_argument("--envs", nargs="+", choices=("office", "house"),
                      default=["office", "house"])
  parser.add_argument("--trajectories", nargs="+", type=int, choices=(0, 1, 2),
                      default=[0, 1, 2])
  parser.add_argument("--train-seeds", nargs="+", type=int, default=list(TRAIN_SEEDS),
                      help="layout seeds of the training sequences")
  parser.add_argument("--validation-seeds", nargs="+", type=int,
                      default=list(VALIDATION_SEEDS),
                      help="layout seeds of the early-stopping sequences (disjoint from the "
                           "training ones)")
  parser.add_argument("--shifts", nargs="+", type=float, default=[0.5, 1.0],
                      help="test-domain shifts the sequences are rendered at")
  parser.add_argument("--steps", type=int, default=150, help="at most this many Adam steps")
  parser.add_argument("--learning-rate", type=float, default=0.05)
  parser.add_argument("--eval-every", type=int, default=10)
  parser.add_argument("--patience", type=int, default=4)
  parser.add_argument("--scalar-beta", action="store_true", help="one β (default: per class)")
  parser.add_argument("--objective", choices=tune.OBJECTIVES, default=tune.DEFAULT_OBJECTIVE,
                      help="the fit's loss: the mean cross-entropy over GT voxels (dominated by "
                           "the most frequent class) or the pooled soft IoU (class-balanced, "
                           "as mIoU)")
  parser.add_argument("--family", choices=learn.FAMILIES, default="learned",
                      help="the rule family to fit: the learned rule (docs/equations.md §3.9), "
                           "GLFS (§3.10, a weight per class × depth bin × incidence bin) or the "
                           "family (§3.11: GLFS's table times an unbounded weight of --terms, "
                           "from --start-table)")
  parser.add_argument("--terms", nargs="*", choices=learn.FAMILY_TERMS, default=["moments"],
                      help="--family family: the terms fitted beside the table (moments: a "
                           "log-weight over the MC moment features; context: over --context; "
                           "beta: R's regularisation; mix: D's concentration; spatial: a per-class "
                           "kernel over the 26 neighbours at read-out, docs/equations.md §4.1)")
  parser.add_argument("--start-table", default=None, metavar="PARAMS_JSON",
                      help="--family family: the GLFS (or family) params.json whose table the "
                           "fit starts from (default: the shipped GLFS table)")
  parser.add_argument("--context", nargs="*", default=[], metavar="FEATURE",
                      help="per-pixel context features the learned weight reads (docs/equations.md "
                           "§2.5): " + ", ".join(context_lib.FEATURES) + "; or 'geometry', "
                           "'image', 'all'")
  parser.add_argument("--per-class-weights", action="store_true",
                      help="one row of weights per predicted class (θ, b, context weights)")
  parser.add_argument("--gate-size", type=int, choices=(3, 5), default=3,
                      help="3: the gate reads agreement and spread; 5: also the frame's "
                           "divergence from the voxel and the voxel's frame count")
  parser.add_argument("--select", choices=learn.SELECTIONS, default="loss",
                      help="what early stopping keeps: the lowest validation loss or the "
                           "highest validation map mIoU")
  parser.add_argument("--out", default=DEFAULT_OUT, help="output folder")
  parser.add_argument("--quick", action="store_true",
                      help="smoke run: one env, one trajectory, one shift, 8 small frames, "
                           "6 steps")
  tuning.add_data_args(parser, rule_help=argparse.SUPPRESS, layout_seeds=False,
                       calibration=True, validation=True)
  parser.set_defaults(func=command, front_end="shipped")


# Named groups of context features (`--context geometry image` etc.).
CONTEXT_GROUPS = {"geometry": ("depth", "incidence", "depth_edge", "label_edge", "radius"),
                  "image": context_lib.IMAGE_FEATURES, "all": context_lib.FEATURES}


def context_names(names: Sequence[str]) -> tuple:
  """Feature names with the groups of `CONTEXT_GROUPS` expanded, in `FEATURES` order."""
  chosen = set()
  for name in names:
    chosen.update(CONTEXT_GROUPS.get(name, (name,)))
  return context_lib.check_names([n for n in context_lib.FEATURES if n in chosen] +
                                 sorted(chosen - set(context_lib.FEATURES)))


def _check_seeds(train: Sequence[int], validation: Sequence[int]) -> None:
  overlap = set(train) & set(validation)
  if overlap:
    raise ValueError(f"training and validation layout seeds must be disjoint; both have "
                     f"{sorted(overlap)}")
  judged = (set(train) | set(validation)) & set(JUDGED_SEEDS)
  if judged:
    raise ValueError(f"layout seeds {sorted(judged)} are those the rules are judged on (demo, "
                     f"study, tuning protocol: {list(JUDGED_SEEDS)}); train on others")


# Parsed arguments that are not options of learn-rule (the sub-command's name, the handler) or
# that it does not read (the tuning commands' rule and single shift).
_NOT_OPTIONS = ("func", "command", "rule", "shift")


def command_line(args) -> str:
  """The `jaxfusion learn-rule` command line that reproduces `args` (every option spelled out)."""
  def value(v):
    return " ".join(str(x) for x in v) if isinstance(v, (list, tuple)) else str(v)
  parts = [f"--{k.replace('_', '-')}" + ("" if v is True else f" {value(v)}")
           for k, v in sorted(vars(args).items())
           if k not in _NOT_OPTIONS and v is not None and v is not False and v != []]
  return " ".join(["jaxfusion learn-rule"] + parts)


def _data_batches(args, given: dict) -> tuple:
  """The training and validation batches of `--calibration-data` and `--validation-data` (a
  researcher's sequences, or embedded specs of layouts no command judges on)."""
  train, validation = given["--calibration-data"], given["--validation-data"]
  if given["--data"] is not None:
    raise ValueError("learn-rule fits on --calibration-data and selects on --validation-data; "
                     "it judges nothing (judge the rule with `jaxfusion study --data ...`)")
  if train is None or validation is None:
    raise ValueError("learn-rule on your data needs both --calibration-data (to fit on) and "
                     "--validation-data (to select on)")
  judged = [str(s) for s in train + validation if s.is_embedded and (
      0 if s.layout_seed is None else s.layout_seed) in JUDGED_SEEDS]
  if judged:
    raise ValueError(f"{judged[0]}: layout seeds {list(JUDGED_SEEDS)} are those the rules are "
                     "judged on (demo, study, tuning protocol); fit on others")
  options = tuning.data_options(args, layout_seed=args.train_seeds[0])
  front_end = tuning.data_front_end(args)
  return (tuning.load_data_batch(train, options, front_end=front_end),
          tuning.load_data_batch(validation, options, front_end=front_end))


def start_table(args) -> np.ndarray:
  """The table `--family family` starts from: `--start-table`'s, or the shipped GLFS table."""
  if args.start_table is None:
    import jaxfusion_models  # pylint: disable=import-outside-toplevel
    args.start_table = str(jaxfusion_models.GLFS_PATH)
  family, params = learn.load_rule(args.start_table)
  if family not in ("glfs", "family") or "table" not in params:
    raise ValueError(f"--start-table {args.start_table}: a {family!r} parameter file without a "
                     f"table (give a GLFS or family params.json)")
  return np.asarray(params["table"], np.float32)


def command(args) -> int:
  """Runs `jaxfusion learn-rule`; returns the exit status."""
  if args.quick:
    args.envs, args.trajectories, args.shifts = args.envs[:1], [0], args.shifts[-1:]
    args.frames, args.height, args.width, args.steps = 8, 30, 40, 6
    args.eval_every, args.patience = 2, 2
  started = time.perf_counter()
  table = start_table(args) if args.family == "family" else None   # refused before the data
  given = flags.data_sets(args, "calibration_data", "validation_data", "data")
  if any(v is not None for v in given.values()):
    train, validation = _data_batches(args, given)
  else:
    _check_seeds(args.train_seeds, args.validation_seeds)
    front_end = tuning.front_end_of(args)
    kwargs = tuning.data_kwargs(args, front_end)

    def load(seeds):
      batches = []
      for shift in args.shifts:
        units = [(e, t, s) for s in seeds for e in args.envs for t in args.trajectories]
        batches.append(tuning.load_sequence_batch(units, **{**kwargs, "shift": shift}))
      return merge_batches(batches)

    train, validation = load(args.train_seeds), load(args.validation_seeds)
  loaded = time.perf_counter() - started
  from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel
  bar = tqdm(total=args.steps, desc="learn-rule", unit="step")

  def progress(step, loss, val):
    bar.update(1)
    bar.set_postfix(loss=f"{loss:.4f}", **({} if val is None else {"val": f"{val:.4f}"}))

  result = learn.fit(train, validation, steps=args.steps, learning_rate=args.learning_rate,
                     eval_every=args.eval_every, patience=args.patience,
                     per_class_beta=not args.scalar_beta, aggregate=args.aggregate,
                     voxel_size=args.voxel_size, select=args.select, progress=progress,
                     objective=args.objective,
                     family=args.family, context=context_names(args.context),
                     per_class_weights=args.per_class_weights, gate_size=args.gate_size,
                     terms=tuple(args.terms),
                     start_table=table)
  bar.close()
  os.makedirs(args.out, exist_ok=True)
  reports.write_json(os.path.join(args.out, "params.json"),
                     {"rule": args.family, "params": result.params}, indent=2)
  record = {
      "command": command_line(args),
      "data": {"train": train["names"], "validation": validation["names"],
               "shifts": args.shifts, "frames": args.frames, "height": args.height,
               "width": args.width, "num_samples": args.num_samples,
               "front_end": train["source"], "voxel_size": args.voxel_size},
      "objective": args.objective, "steps_run": result.steps_run,
      "stopped_early": result.stopped_early, "best_step": result.best_step,
      "train_losses": result.train_losses, "validation": result.validation,
      "select": args.select, "validation_miou": result.validation_miou,
      "seconds": {"data": loaded, "fit": result.seconds,
                  "total": time.perf_counter() - started},
      "validation_ece": {
          "kept": learn.map_calibration(result.rule, validation,
                                        voxel_size=args.voxel_size)["ece"],
          "bayes": learn.map_calibration(rules.bayes(aggregate=args.aggregate), validation,
                                         voxel_size=args.voxel_size)["ece"]},
      "family": args.family, "num_parameters": int(sum(
          np.size(v) for k, v in result.params.items() if k not in ("eps", "alpha0", "context"))),
      "params": result.params}
  reports.write_json(os.path.join(args.out, "record.json"), record, indent=2)
  figures.learned_rule_losses(os.path.join(args.out, "loss.png"), result)
  if args.family == "learned":
    figures.learned_rule_weights(os.path.join(args.out, "weights.png"), result.rule.hparams,
                                 num_classes=train["num_classes"])
  best = dict(result.validation)[result.best_step]
  print(f"{args.family}: best validation loss {best:.4f} at step {result.best_step} of "
        f"{result.steps_run} ({result.seconds:.0f} s fitting); wrote {args.out}/params.json, "
        f"record.json, loss.png" + (", weights.png" if args.family == "learned" else ""))
  return 0


def main(args: argparse.Namespace) -> int:
  """Runs the parsed command."""
  return args.func(args)


