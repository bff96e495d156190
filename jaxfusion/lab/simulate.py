"""`jaxfusion simulate-sweep`: fusion rules on a grid of the simulated front end's parameters.

The simulated front end itself (its generative model, `ErrorModel`, `simulate_sequence`) is the
library's `jaxfusion.simulation`; this module sweeps two of its parameters over embedded
sequences, fuses every cell with Bayes, R, D, D+R and an oracle (and, with `--learned`, the
learned rule fitted for that cell's front end on calibration layouts), and writes the heatmap
and the tables.

Shape legend: T frames, H×W pixels, K classes, X×Y sweep cells, D draws, R rules.
"""

import argparse
import functools
import inspect
import os
import time
from typing import NamedTuple, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import batch
from jaxfusion import camera as camera_lib
from jaxfusion import fusion
from jaxfusion import learn
from jaxfusion import metrics
from jaxfusion import rules as rules_lib
from jaxfusion import state as state_lib
from jaxfusion import tune
from jaxfusion.lab import figures
from jaxfusion.lab import flags
from jaxfusion.lab import reports
from jaxfusion.simulation import REGIONS
from jaxfusion.simulation import SWEEP_PARAMS
from jaxfusion.simulation import ErrorModel
from jaxfusion.simulation import check_frame_arrays
from jaxfusion.simulation import check_regions
from jaxfusion.simulation import error_model
from jaxfusion.simulation import simulate_frame

# The oracle keeps this weight on a wrong pixel's prediction (the rest is uniform): a voxel keeps
# any right evidence and falls back to its wrong votes only when it has no right one.
ORACLE_WEIGHT = 1e-5
# The rules of a sweep by their display names (`rules.display_name`, the study's "Oracle"), in
# the order of its outputs (Bayesian ≡ R with β = 0, D ≡ D+R with β = 0).
SWEEP_RULES = ("Bayesian", "R", "D", "D+R", "Oracle")
# The learned rule's column, after those, when the sweep is given learned rules.
LEARNED = "Learned"


# --- the sweep -----------------------------------------------------------------------------------
def _sweep_rules(beta: float):
  """Two stacks of two rules each: [Bayes ≡ R(β=0), R(β)] and [D ≡ D+R(β=0), D+R(β)]."""
  r_stack = rules_lib.stack([rules_lib.robust(dirichlet=False, beta=0.0),
                             rules_lib.robust(dirichlet=False, beta=beta)])
  dr_stack = rules_lib.stack([rules_lib.robust(beta=0.0), rules_lib.robust(beta=beta)])
  return r_stack, dr_stack


def _views(key, labels, instance_ids, depth, poses, camera, model, *, num_classes, regions):
  """The simulated front end's view of every frame of one sequence (`SimulatedView`, `(T, …)`)."""
  frames_t = jnp.arange(labels.shape[0], dtype=jnp.int32)
  one = functools.partial(simulate_frame, num_classes=num_classes, regions=regions)
  return jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0, None, None))(
      key, labels, instance_ids, frames_t, depth, poses, camera, model)


@functools.partial(jax.jit, static_argnames=(
    "num_classes", "regions", "capacity", "voxel_size", "max_probes"))
def _sweep_row(key, labels, instance_ids, depth, poses, camera, models, gt_coords, gt_labels,
               r_stack, dr_stack, learned_stack=None, *, num_classes, regions, capacity,
               voxel_size, max_probes):
  """Confusions `(X, R, K, K)` of Bayes, R, D, D+R, the oracle (and each cell's learned rule
  when `learned_stack` holds X of them), and the views' `wrong` and α of the favoured class
  `(X, T, H, W)`, for X models (one sweep row) on one sequence."""
  mask = jnp.ones(labels.shape[:1], bool)
  fuse = functools.partial(batch.fuse_masked, capacity=capacity, num_classes=num_classes,
                           voxel_size=voxel_size, max_probes=max_probes)

  def fuse_and_score(frames, rule):
    state = fuse(frames, mask, camera, rule)
    return tune.confusion(state, gt_coords, gt_labels)

  def cell(model_and_rule):
    model, learned = model_and_rule
    view = _views(key, labels, instance_ids, depth, poses, camera, model,
                  num_classes=num_classes, regions=regions)
    frames = fusion.Frame(depth, poses, view.probs, view.var)
    by_rule = jax.vmap(fuse_and_score, in_axes=(None, 0))
    cms_r = by_rule(frames, r_stack)
    cms_dr = by_rule(frames, dr_stack)
    oracle_probs = jnp.where(view.wrong[..., None],
                             ORACLE_WEIGHT * view.probs + (1.0 - ORACLE_WEIGHT) / num_classes,
                             view.probs)
    cm_oracle = fuse_and_score(frames._replace(probs=oracle_probs, var=None),
                               rules_lib.bayes())
    cms = [cms_r, cms_dr, cm_oracle[None]]
    if learned is not None:
      cms.append(fuse_and_score(frames, learned)[None])
    var_f = jnp.take_along_axis(view.var, view.favoured[..., None], axis=-1)[..., 0]
    return jnp.concatenate(cms), view.wrong, -jnp.log(var_f + 1e-12)

  return jax.lax.map(cell, (models, learned_stack))


@functools.partial(jax.jit, static_argnames=("num_classes", "regions"))
def _simulated_moments(key, labels, instance_ids, depth, poses, camera, model, *, num_classes,
                       regions):
  view = _views(key, labels, instance_ids, depth, poses, camera, model, num_classes=num_classes,
                regions=regions)
  return view.probs, view.var


def simulated_batch(sequences: Sequence[dict], model: ErrorModel, *, seed: int = 0,
                    regions: str = "both") -> dict:
  """Sequences seen through the simulated front end `model`, as one batch for `learn.fit`.

  Args:
    sequences: dicts as `sweep_grid` reads them (`load_sequence`).
    model: the front end's `ErrorModel` (one cell of a sweep).
    seed: seed of the draw; sequence i uses key `fold_in(key(seed), i)`.
    regions: "objects", "patches" or "both".

  Returns:
    dict with `names`, `frames` `(B, T, …)`, `mask`, `camera`, `coords`, `labels`, `capacity`,
    `num_classes` (the layout of `lab.tuning.load_sequence_batch`).
  """
  frames, gts = [], []
  for i, seq in enumerate(sequences):
    camera = camera_lib.Camera(*(jnp.float32(v) for v in seq["camera"]))
    probs, var = _simulated_moments(
        jax.random.fold_in(jax.random.PRNGKey(seed), i), jnp.asarray(seq["labels"], jnp.int32),
        jnp.asarray(seq["instances"], jnp.int32), jnp.asarray(seq["depth"], jnp.float32),
        jnp.asarray(seq["T_world_cam"], jnp.float32), camera, model,
        num_classes=int(seq["num_classes"]), regions=regions)
    frames.append(fusion.Frame(np.asarray(seq["depth"], np.float32),
                               np.asarray(seq["T_world_cam"], np.float32), np.asarray(probs),
                               np.asarray(var)))
    gts.append(seq["gt"])
  stacked, mask = batch.stack_sequences(frames)
  coords, labels = tune.pad_ground_truth(gts)
  return {"names": [s["name"] for s in sequences], "frames": stacked, "mask": mask,
          "camera": sequences[0]["camera"], "coords": coords, "labels": labels,
          "capacity": max(state_lib.capacity_for(len(g["labels"])) for g in gts),
          "num_classes": int(sequences[0]["num_classes"])}


def fit_learned_rules(calibration: Sequence[dict], validation: Sequence[dict], *, x_param: str,
                      x_values, y_param: str, y_values, base: Optional[dict] = None,
                      regions: str = "both", seed: int = 0, progress: bool = True,
                      **fit_kwargs) -> list:
  """The learned rule fitted for each cell's front end: `(Y, X)` nested lists of `FitResult`.

  Each cell's simulated front end sees the calibration and validation sequences (other layouts
  than those the sweep judges on) and `learn.fit` fits `rules.learned` on the first, stopping
  early on the second, as `jaxfusion learn-rule` does for the network.

  Args:
    calibration: training sequences (`load_sequence` dicts).
    validation: early-stopping sequences.
    x_param, x_values, y_param, y_values, base, regions: the sweep's grid (see `sweep_grid`).
    seed: seed of the calibration draws (validation uses `seed + 1`).
    progress: show a tqdm bar over cells.
    **fit_kwargs: passed to `learn.fit` (steps, learning_rate, eval_every, patience, ...).
  """
  from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel
  rows = _grid(calibration, x_param=x_param, x_values=x_values, y_param=y_param,
               y_values=y_values, base=base).models
  bar = tqdm(total=sum(len(r) for r in rows), desc="fit learned rules", disable=not progress)
  fits = []
  for row in rows:
    fits.append([])
    for model in row:
      train = simulated_batch(calibration, model, seed=seed, regions=regions)
      val = simulated_batch(validation, model, seed=seed + 1, regions=regions)
      fits[-1].append(learn.fit(train, val, **fit_kwargs))
      bar.update(1)
  bar.close()
  return fits


class _Grid(NamedTuple):
  """A checked sweep grid: the X and Y values (floats), the fixed fields, K and the `(Y, X)`
  nested lists of the cells' `ErrorModel`s."""
  x_values: list
  y_values: list
  base: dict
  num_classes: int
  models: list


def _grid(sequences, *, x_param, x_values, y_param, y_values, base) -> _Grid:
  """Checks the axes, the base and the sequences' K, and builds every cell's `ErrorModel`."""
  for name in (x_param, y_param):
    if name not in SWEEP_PARAMS:
      raise ValueError(f"a sweep axis must be one of {SWEEP_PARAMS}; got {name!r}")
  if x_param == y_param:
    raise ValueError(f"the two axes must differ; got {x_param!r} twice")
  x_values = [float(v) for v in x_values]
  y_values = [float(v) for v in y_values]
  if not x_values or not y_values:
    raise ValueError("each axis needs at least one value")
  if not sequences:
    raise ValueError("a sweep needs at least one sequence")
  base = dict(base or {})
  unknown = sorted(set(base) - set(SWEEP_PARAMS))
  if unknown:
    raise ValueError(f"unknown base parameters {unknown}; known: {list(SWEEP_PARAMS)}")
  for name in (x_param, y_param):
    base.pop(name, None)
  num_classes = {int(s["num_classes"]) for s in sequences}
  if len(num_classes) != 1:
    raise ValueError(f"all sequences must have the same K; got {sorted(num_classes)}")
  (num_classes,) = num_classes
  models = [[error_model(num_classes=num_classes, **base, **{x_param: xv, y_param: yv})
             for xv in x_values] for yv in y_values]
  return _Grid(x_values, y_values, base, num_classes, models)


def _stack_models(models: Sequence[ErrorModel]) -> ErrorModel:
  return jax.tree.map(lambda *xs: jnp.stack(xs), *models)


def sweep_grid(sequences: Sequence[dict], *, x_param: str, x_values, y_param: str, y_values,
               base: Optional[dict] = None, regions: str = "both", beta: float = 0.3,
               num_draws: int = 1, seed: int = 0, voxel_size: float = 0.1,
               max_probes: int = state_lib.DEFAULT_MAX_PROBES, progress: bool = True,
               learned: Optional[Sequence[Sequence[rules_lib.FusionRule]]] = None) -> dict:
  """Fuses sequences seen through the simulated front end on a grid of two of its parameters.

  Every cell of the X×Y grid is fused with Bayes, R, D, D+R (two vmapped stacks: Bayes is R
  with β = 0 and D is D+R with β = 0, the same equations) and the oracle — Bayes after every
  wrong pixel's prediction is replaced by `ORACLE_WEIGHT·p̄ + (1 − ORACLE_WEIGHT)/K`, so a voxel
  keeps all its right evidence and is decided by its wrong votes only when it has no right one:
  roughly the best any rule that reweights observations can do. One sweep row (X cells) is one
  jitted call per sequence and draw; draw d of sequence i uses key `fold_in(fold_in(key(seed),
  i), d)` in every cell (common random numbers). Confusions are summed over sequences per draw.

  Args:
    sequences: dicts with `labels`, `instances`, `depth` `(T, H, W)`, `T_world_cam (T, 4, 4)`,
      `camera`, `gt` (`coords (N, 3)`, `labels (N,)`), `num_classes`, and `name`.
    x_param: the ErrorModel field on the x axis (one of `SWEEP_PARAMS`).
    x_values: its X values.
    y_param: the field on the y axis.
    y_values: its Y values.
    base: the other fields (default: `error_model`'s defaults).
    regions: "objects", "patches" or "both".
    beta: β of R and D+R.
    num_draws: D independent draws of the front end per sequence.
    seed: seed of the draws.
    voxel_size: voxel edge in metres (the GT's).
    max_probes: hash probe bound.
    progress: show a tqdm bar.
    learned: `(Y, X)` nested lists of learned rules (`rules.learned`, e.g. each cell's
      `fit_learned_rules` result), fused on the same views as a sixth column `LEARNED`.

  Returns:
    dict with `rules` (`SWEEP_RULES`, then `LEARNED` when given), `x`/`y` (values),
    `miou`/`accuracy` `(Y, X, D, R)`,
    `confusion (Y, X, D, R, K, K)`, realised `error_rate`, `alpha_separation`, `auroc`
    `(Y, X)` (over all sequences and draws), and `seconds`.
  """
  from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel
  if int(num_draws) < 1:
    raise ValueError(f"num_draws must be ≥ 1; got {num_draws}")
  check_regions(regions)
  x_values, y_values, base, num_classes, rows = _grid(
      sequences, x_param=x_param, x_values=x_values, y_param=y_param, y_values=y_values,
      base=base)
  learned_rows = [None] * len(rows)
  if learned is not None:
    if len(learned) != len(y_values) or any(len(r) != len(x_values) for r in learned):
      raise ValueError(f"learned must hold {len(y_values)}×{len(x_values)} rules, one per cell")
    learned_rows = [rules_lib.stack(list(r)) for r in learned]
  r_stack, dr_stack = _sweep_rules(beta)
  names = list(SWEEP_RULES) + ([LEARNED] if learned is not None else [])
  num_rules = len(names)
  shape = (len(y_values), len(x_values), int(num_draws))
  cms = np.zeros(shape + (num_rules, num_classes, num_classes), np.int64)
  tallies = {}      # per cell: lists of α for right / wrong pixels, counts
  start = time.perf_counter()
  bar = tqdm(total=len(y_values) * len(sequences) * num_draws, desc="simulate-sweep",
             disable=not progress)
  for i, seq in enumerate(sequences):
    labels = jnp.asarray(seq["labels"], jnp.int32)
    instances = jnp.asarray(seq["instances"], jnp.int32)
    depth = jnp.asarray(seq["depth"], jnp.float32)
    poses = jnp.asarray(seq["T_world_cam"], jnp.float32)
    camera = camera_lib.Camera(*(jnp.float32(v) for v in seq["camera"]))
    check_frame_arrays(labels, instances, depth, poses, seq["camera"], regions,
                        lead=(labels.shape[0],))
    gt_coords = jnp.asarray(seq["gt"]["coords"], jnp.int32)
    gt_labels = jnp.asarray(seq["gt"]["labels"], jnp.int32)
    capacity = state_lib.capacity_for(len(seq["gt"]["labels"]))
    valid = np.asarray((seq["depth"] > 0) & (seq["labels"] >= 0)
                       & (seq["labels"] < num_classes))
    sizes = dict(num_classes=num_classes, regions=regions, capacity=capacity,
                 voxel_size=float(voxel_size), max_probes=max_probes)
    for d in range(int(num_draws)):
      key = jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(seed), i), d)
      for yi, row in enumerate(rows):
        out_cms, wrong, alpha = _sweep_row(
            key, labels, instances, depth, poses, camera, _stack_models(row), gt_coords,
            gt_labels, r_stack, dr_stack, learned_rows[yi], **sizes)
        cms[yi, :, d] += np.asarray(out_cms)
        wrong, alpha = np.asarray(wrong), np.asarray(alpha)
        for xi in range(len(x_values)):
          w, a = wrong[xi][valid], alpha[xi][valid]
          t = tallies.setdefault((yi, xi), {"right": [], "wrong": [], "n": 0, "n_wrong": 0})
          # A fixed subsample keeps the α statistics cheap on long sweeps.
          t["right"].append(a[~w][::7])
          t["wrong"].append(a[w][::7])
          t["n"] += int(w.size)
          t["n_wrong"] += int(w.sum())
        bar.update(1)
  bar.close()
  seconds = time.perf_counter() - start
  flat = cms.reshape((-1, num_classes, num_classes))
  miou = np.array([metrics.mean_iou(c) for c in flat]).reshape(shape + (num_rules,))
  acc = np.array([metrics.accuracy(c) for c in flat]).reshape(shape + (num_rules,))
  realised = {k: np.full(shape[:2], np.nan) for k in ("error_rate", "alpha_separation",
                                                     "auroc")}
  for (yi, xi), t in tallies.items():
    right, wrong = np.concatenate(t["right"]), np.concatenate(t["wrong"])
    realised["error_rate"][yi, xi] = t["n_wrong"] / max(t["n"], 1)
    if len(right) and len(wrong):
      realised["alpha_separation"][yi, xi] = np.median(right) - np.median(wrong)
      realised["auroc"][yi, xi] = metrics.auroc_of_samples(right, wrong)
  return {"rules": names, "x_param": x_param, "y_param": y_param,
          "x": x_values, "y": y_values, "base": {k: float(v) for k, v in base.items()},
          "regions": regions, "beta": float(beta), "num_draws": int(num_draws),
          "sequences": [s["name"] for s in sequences], "miou": miou, "accuracy": acc,
          "confusion": cms, "seconds": seconds, **realised}


# --- tables --------------------------------------------------------------------------------------
def _rows(result: dict) -> list:
  rows = []
  miou, acc = result["miou"], result["accuracy"]
  for yi, yv in enumerate(result["y"]):
    for xi, xv in enumerate(result["x"]):
      row = {result["y_param"]: yv, result["x_param"]: xv}
      for r, name in enumerate(result["rules"]):
        row[f"miou_{name}"] = float(np.mean(miou[yi, xi, :, r]))
        row[f"accuracy_{name}"] = float(np.mean(acc[yi, xi, :, r]))
      diff = miou[yi, xi, :, result["rules"].index("D+R")] - miou[yi, xi, :, 0]
      row["miou_DR_minus_Bayes"] = float(np.mean(diff))
      row["miou_DR_minus_Bayes_std"] = float(np.std(diff))
      head = miou[yi, xi, :, result["rules"].index("Oracle")] - miou[yi, xi, :, 0]
      row["miou_oracle_minus_Bayes"] = float(np.mean(head))
      row["oracle_share_DR"] = _share(np.mean(diff), np.mean(head))
      if LEARNED in result["rules"]:
        learned = miou[yi, xi, :, result["rules"].index(LEARNED)]
        row["miou_Learned_minus_Bayes"] = float(np.mean(learned - miou[yi, xi, :, 0]))
        row["miou_Learned_minus_DR"] = float(np.mean(
            learned - miou[yi, xi, :, result["rules"].index("D+R")]))
        row["miou_Learned_minus_DR_std"] = float(np.std(
            learned - miou[yi, xi, :, result["rules"].index("D+R")]))
        row["oracle_share_Learned"] = _share(row["miou_Learned_minus_Bayes"], np.mean(head))
      for k in ("error_rate", "alpha_separation", "auroc"):
        row[f"realised_{k}"] = float(result[k][yi, xi])
      rows.append(row)
  return rows


def _share(gain: float, headroom: float) -> float:
  """A rule's mIoU gain over Bayes as a share of the oracle's (NaN without headroom)."""
  return float(gain / headroom) if headroom > 0 else float("nan")


def write_results(out_dir: str, result: dict) -> list:
  """Writes `heatmap.png`, `results.csv` (one row per cell) and `results.json` under out_dir."""
  os.makedirs(out_dir, exist_ok=True)
  rows = _rows(result)
  paths = [os.path.join(out_dir, n) for n in ("heatmap.png", "results.csv", "results.json")]
  figures.simulation_heatmap(paths[0], result)
  reports.write_csv(paths[1], ([f"{v:.5g}" for v in row.values()] for row in rows),
                    header=list(rows[0]))
  payload = {k: result[k] for k in ("rules", "x_param", "y_param", "x", "y", "base", "regions",
                                    "beta", "num_draws", "sequences", "seconds")}
  payload["settings"] = result.get("settings", {})
  payload["cells"] = rows
  payload["miou"] = np.asarray(result["miou"]).tolist()
  if "learned" in result:
    payload["learned"] = result["learned"]
  reports.write_json(paths[2], payload)
  return paths


# --- command line --------------------------------------------------------------------------------
def load_sequence(spec: str, *, num_frames: int, height: int, width: int, seed: int,
                  voxel_size: float, shift: float = 1.0) -> dict:
  """An embedded sequence ("ENV:TRAJECTORY[:DOMAIN]") as the dict `sweep_grid` reads."""
  from jaxfusion import datasets  # pylint: disable=import-outside-toplevel
  parsed = datasets.parse_spec(spec)
  if parsed.kind != "synthetic":
    raise ValueError(f"simulate-sweep runs on embedded sequences (ENV:TRAJECTORY); got {spec!r}")
  seq = datasets.load_spec(parsed, num_frames=num_frames, height=height, width=width,
                           layout_seed=seed, shift=shift)
  gt = datasets.gt_voxel_labels(seq, voxel_size=voxel_size)
  return {"name": datasets.unit_name(seq.name, seed), "labels": seq.labels,
          "instances": seq.instances, "depth": seq.depth, "T_world_cam": seq.T_world_cam,
          "camera": seq.camera, "gt": gt, "num_classes": seq.num_classes}


def _floats(text: str) -> list:
  try:
    values = [float(v) for v in text.split(",") if v.strip()]
  except ValueError:
    raise ValueError(f"expected comma-separated numbers; got {text!r}") from None
  if not values:
    raise ValueError(f"expected at least one number; got {text!r}")
  return values


_QUICK = {"sequences": "office:0", "frames": 12, "height": 48, "width": 64, "draws": 1,
          "x_values": "0,0.5,1", "y_values": "0,2,4"}
_FULL = {"sequences": "office:0,house:2", "frames": 30, "height": 90, "width": 120, "draws": 3,
         "x_values": "0,0.25,0.5,0.75,1", "y_values": "0,1,2,3,4"}


def add_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `simulate-sweep`: D+R − Bayes on a grid of the simulated front end's parameters."""
  parser = subparsers.add_parser(
      "simulate-sweep",
      help="heatmap of D+R − Bayes over two parameters of a simulated view-dependent front end",
      description="Sees embedded sequences through a simulated Bayesian front end whose errors "
                  "are spatially coherent (objects and world patches) and partly correlated "
                  "across views (jaxfusion.simulation), fuses them with Bayes, R, D, D+R and an "
                  "oracle on a grid of two of its parameters, and writes heatmap.png, "
                  "results.csv and results.json.")
  parser.add_argument("--quick", action="store_true",
                      help="a 3×3 grid on one short, small sequence, one draw (about 30 s of "
                           "CPU, plus rendering)")
  parser.add_argument("--out", default="outputs/simulate_sweep", help="output folder")
  parser.add_argument("--x", default="cross_view_correlation", choices=SWEEP_PARAMS)
  parser.add_argument("--y", default="variance_separation", choices=SWEEP_PARAMS)
  parser.add_argument("--x-values", default=None, help="comma-separated values of --x")
  parser.add_argument("--y-values", default=None, help="comma-separated values of --y")
  parser.add_argument("--sequences", default=None, help="comma-separated ENV:TRAJECTORY list")
  parser.add_argument("--frames", type=int, default=None)
  parser.add_argument("--height", type=int, default=None)
  parser.add_argument("--width", type=int, default=None)
  parser.add_argument("--draws", type=int, default=None, help="draws of the front end")
  flags.add_layout_seeds(parser, default=[0], aliases=("--scene-seed",),
                         help_suffix=" (one; default 0)")
  flags.add_mc_seed(parser, aliases=("--seed",), what="the simulated front end")
  parser.add_argument("--regions", choices=REGIONS, default="both")
  parser.add_argument("--beta", type=float, default=0.3, help="β of R and D+R")
  parser.add_argument("--voxel-size", type=float, default=0.1)
  parser.add_argument("--learned", action="store_true",
                      help="also fit the learned rule (rules.learned) for each cell's front end "
                           "on calibration layouts (--learned-seeds) and fuse it as a sixth "
                           "column")
  parser.add_argument("--learned-seeds", nargs=2, type=int, default=[11, 12],
                      metavar=("TRAIN", "VALIDATION"),
                      help="layout seeds of the learned rule's training and early-stopping "
                           "sequences (the same ENV:TRAJECTORY list; default 11 12)")
  parser.add_argument("--learned-steps", type=int, default=40, help="at most this many steps")
  parser.add_argument("--learned-eval-every", type=int, default=5)
  parser.add_argument("--learned-patience", type=int, default=3)
  parser.add_argument("--learned-select", choices=learn.SELECTIONS, default="loss",
                      help="what each fit's early stopping keeps: the lowest validation loss "
                           "or the highest validation map mIoU")
  # The defaults from error_model's signature, not from calling it: building the parser must
  # not start JAX's backend (a `--processes` run joins the distributed runtime after parsing).
  defaults = {name: p.default for name, p in inspect.signature(error_model).parameters.items()
              if p.default is not inspect.Parameter.empty}
  defaults["error_rate"] = 0.3
  for name in SWEEP_PARAMS:
    parser.add_argument(f"--{name.replace('_', '-')}", type=float,
                        default=float(defaults[name]),
                        help=f"fixed value when not on an axis (default {float(defaults[name]):g})")
  parser.set_defaults(func=main)
  return parser


def main(args: argparse.Namespace) -> int:
  """Runs `jaxfusion simulate-sweep`; returns the exit status."""
  preset = _QUICK if args.quick else _FULL
  pick = lambda name: preset[name] if getattr(args, name) is None else getattr(args, name)
  for name in ("frames", "height", "width", "draws"):
    if pick(name) < 1:
      raise ValueError(f"--{name} must be at least 1")
  specs = [s.strip() for s in pick("sequences").split(",") if s.strip()]
  start = time.perf_counter()
  sequences = [load_sequence(s, num_frames=pick("frames"), height=pick("height"),
                             width=pick("width"), seed=flags.one_layout_seed(args),
                             voxel_size=args.voxel_size) for s in specs]
  render_seconds = time.perf_counter() - start
  base = {name: getattr(args, name) for name in SWEEP_PARAMS}
  grid = dict(x_param=args.x, x_values=_floats(pick("x_values")), y_param=args.y,
              y_values=_floats(pick("y_values")), base=base, regions=args.regions)
  learned, record = None, None
  if args.learned:
    judged = flags.one_layout_seed(args)
    seeds = [int(v) for v in args.learned_seeds]
    if len(set(seeds + [judged])) < 3:
      raise ValueError(f"--learned-seeds {seeds} must differ from each other and from the "
                       f"layout seed the sweep judges on ({judged})")
    calibration = [[load_sequence(s, num_frames=pick("frames"), height=pick("height"),
                                  width=pick("width"), seed=seed, voxel_size=args.voxel_size)
                    for s in specs] for seed in seeds]
    fits = fit_learned_rules(*calibration, **grid, seed=args.mc_seed + 1,
                             steps=args.learned_steps, eval_every=args.learned_eval_every,
                             patience=args.learned_patience, voxel_size=args.voxel_size,
                             select=args.learned_select)
    learned = [[f.rule for f in row] for row in fits]
    record = {"train_seed": seeds[0], "validation_seed": seeds[1], "select": args.learned_select,
              "cells": [[{"params": f.params, "best_step": f.best_step,
                          "steps_run": f.steps_run, "validation": f.validation,
                          "validation_miou": f.validation_miou,
                          "seconds": f.seconds} for f in row] for row in fits]}
  result = sweep_grid(sequences, **grid, beta=args.beta, num_draws=pick("draws"),
                      seed=args.mc_seed, voxel_size=args.voxel_size, learned=learned)
  if record is not None:
    result["learned"] = record
  result["settings"] = {"frames": pick("frames"), "height": pick("height"),
                        "width": pick("width"), "scene_seed": flags.one_layout_seed(args),
                        "seed": args.mc_seed, "voxel_size": args.voxel_size,
                        "render_seconds": render_seconds, "quick": bool(args.quick)}
  paths = write_results(args.out, result)
  bayes = result["miou"][..., 0].mean(-1)
  gain = (result["miou"][..., SWEEP_RULES.index("D+R")] - result["miou"][..., 0]).mean(-1)
  head = (result["miou"][..., SWEEP_RULES.index("Oracle")] - result["miou"][..., 0]).mean(-1)
  print(f"{len(specs)} sequence(s) × {pick('draws')} draw(s), {len(result['y'])}×"
        f"{len(result['x'])} cells: {result['seconds']:.1f} s fusing (+ {render_seconds:.1f} s "
        "rendering)")
  print(f"rows: {args.y}; columns: {args.x}")
  print("  Bayesian mIoU / D+R − Bayesian / Oracle − Bayesian (mIoU points):")
  for yi, yv in enumerate(result["y"]):
    cells = "  ".join(f"{100 * bayes[yi, xi]:5.1f} {100 * gain[yi, xi]:+5.1f} "
                      f"{100 * head[yi, xi]:+5.1f}" for xi in range(len(result["x"])))
    print(f"  {yv:>6g} | {cells}")
  if learned is not None:
    lgain = (result["miou"][..., result["rules"].index(LEARNED)] - result["miou"][..., 0]).mean(-1)
    print("  Learned − Bayesian / Learned − D+R (mIoU points) / share of the oracle's headroom "
          "(Learned, D+R):")
    for yi, yv in enumerate(result["y"]):
      cells = "  ".join(
          f"{100 * lgain[yi, xi]:+5.1f} {100 * (lgain - gain)[yi, xi]:+5.1f} "
          f"{_share(lgain[yi, xi], head[yi, xi]):4.0%} {_share(gain[yi, xi], head[yi, xi]):4.0%}"
          for xi in range(len(result["x"])))
      print(f"  {yv:>6g} | {cells}")
  print(f"wrote {', '.join(paths)}")
  return 0
