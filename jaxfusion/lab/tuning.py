"""Tuning protocols and commands: `jaxfusion sweep`, `tune-beta`, `tune-compare`, `tune-protocol`.

The maths (sweeps, surrogate losses, `tune_hparams`) is the library's `jaxfusion.tune`; this
module loads embedded sequences with a front end, runs the protocols on them (do the
surrogates' optima track the mIoU's; tune on calibration layouts, judge on held-out ones) and
formats, plots and writes what they find.

Shape legend: R rules, B sequences, T frames, H×W pixels, K classes, N GT voxels.
"""

import argparse
import math
import time
from typing import Optional, Sequence

import jax
import numpy as np

from jaxfusion import batch
from jaxfusion import fusion
from jaxfusion import metrics
from jaxfusion import rules as rules_lib
from jaxfusion import state as state_lib
from jaxfusion import tune as tune_lib
from jaxfusion.lab import figures
from jaxfusion.lab import flags
from jaxfusion.lab import frontend
from jaxfusion.lab import reports
from jaxfusion.lab import stats
from jaxfusion.tune import DEFAULT_OBJECTIVE
from jaxfusion.tune import OBJECTIVES
from jaxfusion.tune import check_objective
from jaxfusion.tune import evaluate_rules
from jaxfusion.tune import pad_ground_truth
from jaxfusion.tune import sweep_beta
from jaxfusion.tune import tune_hparams


# --- data: embedded sequences with a simulated network, the shipped one or precomputed files ---
DEFAULT_CACHE_DIR = "outputs/cache"
FRONT_ENDS = ("simulated", "shipped")


def load_calibration_sequence(spec: str, *, num_frames: int, height: int, width: int,
                              voxel_size: float, seed: int = 0,
                              predictions: Optional[str] = None, num_samples: int = 8,
                              key_seed: int = 0, shift: float = 1.0, front_end=None,
                              cache_dir: Optional[str] = None) -> dict:
  """An embedded sequence with GT voxel labels and front-end outputs, ready to sweep or tune.

  Args:
    spec: an embedded sequence, "ENV:TRAJECTORY[:DOMAIN]", e.g. "office:0"
      (`datasets.parse_spec`).
    num_frames: T.
    height: H.
    width: W.
    voxel_size: voxel edge in metres for the GT (and the maps).
    seed: layout seed of the embedded world.
    predictions: a folder with one sub-folder per sequence name (e.g. `office_0_test/`) of
      per-frame `.npz` predictions (`frontend.precomputed_predictions`).
    num_samples: M (MC-dropout samples of the network, or of the simulated one).
    key_seed: seed of the MC samples (`--mc-seed`).
    shift: the test domain's shift in [0, 1].
    front_end: a network front end (`frontend.FrontEnd()`, or any object of that protocol):
      its MC mean and variance are computed once per sequence and cached on disk
      (`frontend.cached_predictions`). None, and no `predictions`: the simulated network
      (`frontend.simulated_predictions`).
    cache_dir: the front end's cache folder (default `outputs/cache`).

  Returns:
    dict with `name` (`datasets.unit_name`), `frames` (a Frame with a leading T axis),
    `camera`, `gt` (dict with `coords`, `labels`), `num_classes`, `capacity`
    (`capacity_for` the GT voxels), `source`.
  """
  from jaxfusion import datasets  # pylint: disable=import-outside-toplevel
  if front_end is not None and predictions is not None:
    raise ValueError("give either a front end or a predictions folder, not both")
  parsed = datasets.parse_spec(spec)
  if parsed.kind != "synthetic":
    raise ValueError(f"the tuning commands run on embedded sequences (ENV:TRAJECTORY); got "
                     f"{spec!r}")
  seq = datasets.load_spec(parsed, num_frames=num_frames, height=height, width=width,
                           layout_seed=seed, shift=shift)
  gt = datasets.gt_voxel_labels(seq, voxel_size=voxel_size)
  num_classes = seq.num_classes
  if front_end is not None:
    cache_dir = cache_dir or DEFAULT_CACHE_DIR
    preds = frontend.cached_predictions(front_end, seq, layout_seed=int(seed), shift=shift,
                                        num_samples=num_samples, mc_seed=int(key_seed),
                                        cache_dir=cache_dir)
    source = f"network {front_end.model_id} (MC dropout, M={num_samples}; cache {cache_dir})"
  elif predictions is None:
    preds = frontend.simulated_predictions(seq.labels, env=parsed.env,
                                           trajectory=parsed.trajectory,
                                           num_classes=num_classes, num_samples=num_samples,
                                           mc_seed=key_seed)
    source = f"simulated network (M={num_samples})"
  else:
    preds = frontend.precomputed_predictions(f"{predictions}/{seq.name}", seq)
    source = f"precomputed predictions in {predictions}/{seq.name}"
  var = preds["var"]
  frames = fusion.Frame(np.asarray(seq.depth, np.float32),
                        np.asarray(seq.T_world_cam, np.float32),
                        np.asarray(preds["mean"], np.float32),
                        None if var is None else np.asarray(var, np.float32),
                        np.asarray(seq.rgb, np.uint8))
  return {"name": datasets.unit_name(seq.name, seed), "frames": frames, "camera": seq.camera,
          "gt": gt, "num_classes": num_classes, "source": source,
          "capacity": state_lib.capacity_for(len(gt["labels"]))}


def load_data_sequence(spec, options, *, front_end=None) -> dict:
  """A sequence of `--data` (any spec: a folder of your data or an embedded one) with GT voxel
  labels and predictions (`lab.sequences.load`), as `load_calibration_sequence` returns it.

  Args:
    spec: a spec string or `SequenceSpec`.
    options: `lab.sequences.DataOptions`.
    front_end: a network front end, `sequences.SIMULATED`, or None with `options.predictions`.
  """
  from jaxfusion.lab import sequences  # pylint: disable=import-outside-toplevel
  item = sequences.load(spec, options, front_end=front_end)
  seq, preds = item.sequence, item.predictions
  return {"name": item.name, "frames": frames_of(seq, preds), "camera": seq.camera, "gt": item.gt,
          "num_classes": int(preds["mean"].shape[-1]), "source": item.source,
          "class_names": item.class_names,
          "capacity": data_capacity(item.gt)}


def frames_of(sequence, predictions: dict, *, rgb: bool = True) -> fusion.Frame:
  """The Frame (leading time axis) of a sequence's depth and poses with its predictions'
  MC mean and variance, and (with `rgb`) its colour images."""
  var = predictions["var"]
  return fusion.Frame(np.asarray(sequence.depth, np.float32),
                      np.asarray(sequence.T_world_cam, np.float32),
                      np.asarray(predictions["mean"], np.float32),
                      None if var is None else np.asarray(var, np.float32),
                      np.asarray(sequence.rgb, np.uint8) if rgb else None)


# Map slots per GT voxel for a researcher's data: its maps also hold the voxels of pixels whose
# GT class is ignored (e.g. ScanNet's walls in the 12-class space), which the GT leaves out.
DATA_SLOTS_PER_GT_VOXEL = 4


def data_capacity(gt: dict) -> int:
  """Map capacity for a `--data` sequence: `capacity_for` 4 × its GT voxels (a map that still
  fills reports its dropped voxels: `report_dropped`)."""
  return state_lib.capacity_for(DATA_SLOTS_PER_GT_VOXEL * max(len(gt["labels"]), 1))


def report_dropped(out: dict, name: str) -> None:
  """One line when a sweep's maps dropped voxels (a full map is reported, never silent)."""
  dropped = int(np.max(out.get("dropped", 0)))
  if dropped:
    print(f"warning: {name}: the maps filled and dropped up to {dropped} voxel observations; "
          "the scores are of truncated maps")


def stream_sweep(spec, options, betas, *, rule: str = "D+R", aggregate: str = "sum",
                 front_end=None) -> tuple:
  """A β sweep of one `--data` sequence streamed from disk a chunk at a time
  (`lab.sequences.Streamed`, `tune.sweep_chunks`): GT in a first pass, the R maps carried
  over the chunks in a second.

  Returns:
    `(data, out)`: `data` with `name`, `source`, `gt`; `out` as `sweep_beta`'s.
  """
  from jaxfusion.lab import sequences  # pylint: disable=import-outside-toplevel
  if front_end == sequences.SIMULATED:
    return _in_memory_sweep(spec, options, betas, rule=rule, aggregate=aggregate)
  item = sequences.Streamed(spec, options, front_end=front_end)
  gt = item.gt()
  stacked = rules_lib.stack([rules_lib.by_name(rule, beta=float(b), aggregate=aggregate)
                             for b in betas])
  chunks = (frames_of(c, p) for c, p in item.chunks())
  out = tune_lib.sweep_chunks(chunks, item.camera, gt["coords"], gt["labels"], stacked,
                              capacity=data_capacity(gt),
                              voxel_size=options.voxel_size)
  out["beta"] = np.asarray(betas, np.float32)
  report_dropped(out, item.name)
  return {"name": item.name, "source": item.source, "gt": gt}, out


def _in_memory_sweep(spec, options, betas, *, rule, aggregate) -> tuple:
  from jaxfusion.lab import sequences  # pylint: disable=import-outside-toplevel
  data = load_data_sequence(spec, options, front_end=sequences.SIMULATED)
  out = sweep_beta(data["frames"], data["camera"], data["gt"]["coords"], data["gt"]["labels"],
                   betas=betas, rule=rule, capacity=data["capacity"],
                   voxel_size=options.voxel_size, aggregate=aggregate)
  return data, out


def batch_of(datas: Sequence[dict]) -> dict:
  """B loaded sequences (`load_calibration_sequence` / `load_data_sequence` outputs) as one
  padded batch, for `tune_hparams`, `sweep` and `evaluate_rules`."""
  if not datas:
    raise ValueError("a batch needs at least one sequence")
  cameras = {tuple(float(c) for c in d["camera"]) for d in datas}
  if len(cameras) != 1:
    raise ValueError(f"the sequences of a batch must share one camera; got {sorted(cameras)}")
  sizes = {tuple(np.shape(d["frames"].depth)[1:]) for d in datas}
  if len(sizes) != 1:
    raise ValueError(f"the sequences of a batch must share one image size; got {sorted(sizes)}")
  ks = {d["num_classes"] for d in datas}
  if len(ks) != 1:
    raise ValueError(f"the sequences of a batch must share one label space; got K = {sorted(ks)}")
  frames, mask = batch.stack_sequences([d["frames"] for d in datas])
  coords, labels = pad_ground_truth([d["gt"] for d in datas])
  return {"names": [d["name"] for d in datas], "frames": frames, "mask": mask,
          "camera": datas[0]["camera"], "coords": coords, "labels": labels,
          "capacity": max(d["capacity"] for d in datas), "num_classes": datas[0]["num_classes"],
          "source": datas[0]["source"]}


def load_data_batch(specs, options, *, front_end=None) -> dict:
  """`batch_of` the `load_data_sequence` of each spec."""
  from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel
  return batch_of([load_data_sequence(s, options, front_end=front_end)
                   for s in tqdm(list(specs), desc="sequences", leave=False)])


def load_sequence_batch(units: Sequence[tuple], **kwargs) -> dict:
  """B sequences as one padded batch, for `tune_hparams`, `sweep` and `evaluate_rules`.

  Args:
    units: `[(env, trajectory, layout_seed)]`.
    **kwargs: passed to `load_calibration_sequence` (sizes, front end, …).

  Returns:
    dict with `names` (B), `frames` (`(B, T, …)`), `mask` `(B, T)`, `camera`, `coords`
    `(B, N, 3)`, `labels` `(B, N)` (−1 padding), `capacity`, `num_classes`, `source`.
  """
  from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel
  if not units:
    raise ValueError("load_sequence_batch needs at least one (env, trajectory, seed) unit")
  return batch_of([load_calibration_sequence(f"{env}:{traj}", seed=int(seed), **kwargs)
                   for env, traj, seed in tqdm(units, desc="sequences", leave=False)])


# --- do the surrogates' optima track the mIoU's? -----------------------------------------------
def _ranks(x: np.ndarray) -> np.ndarray:
  """Average ranks (ties share the mean rank)."""
  x = np.asarray(x, np.float64)
  order = np.argsort(x, kind="stable")
  ranks = np.empty(len(x))
  ranks[order] = np.arange(len(x), dtype=np.float64)
  for value in np.unique(x):
    tie = x == value
    ranks[tie] = ranks[tie].mean()
  return ranks


def spearman(a, b) -> float:
  """Spearman rank correlation of two equal-length vectors (NaN if one is constant)."""
  ra, rb = _ranks(a), _ranks(b)
  ra, rb = ra - ra.mean(), rb - rb.mean()
  denom = math.sqrt(float(np.sum(ra * ra) * np.sum(rb * rb)))
  return float(np.sum(ra * rb) / denom) if denom > 0 else float("nan")


def compare_objectives(calibration: dict, held_out: dict, *, rule: str = "D+R", betas=None,
                       steps: int = 40, learning_rate: float = 0.1, init_beta: float = 0.3,
                       aggregate: str = "sum", voxel_size: float = 0.1, mesh=None) -> dict:
  """How well each surrogate's optimum matches the mIoU optimum of a β sweep.

  For each objective in `OBJECTIVES`, β is tuned by gradient on the calibration batch
  (`tune_hparams`), and scored on the held-out batch; a β grid is swept on both batches to
  give the mIoU curve and each surrogate's curve (the exact batch losses `tune_hparams`
  minimises). mIoU is pooled over the sequences of a batch (confusions summed).

  Args:
    calibration: a batch from `load_sequence_batch` to tune on.
    held_out: a batch to judge on.
    rule: "R" or "D+R".
    betas: the sweep grid (default 0, 0.05, …, 1).
    steps: Adam steps of each tuning run.
    learning_rate: Adam step size (in logit β).
    init_beta: start of each tuning run.
    aggregate: pixel aggregation of the rule.
    voxel_size: voxel edge (the GT's).
    mesh: shard the sweeps over devices.

  Returns:
    dict with `betas`, `grid` (per batch: `miou`, and per objective its loss, each `(R,)`),
    `best_beta` (per batch: the grid's mIoU argmax), `objectives` (per objective: `beta_star`
    (gradient), `grid_argmin` (per batch), `spearman` (per batch: rank correlation of −loss
    with mIoU over the grid), `held_out_miou` at β*, `distance` |β* − held-out best β| and
    `regret` (held-out best grid mIoU − mIoU at β*), `losses`, `seconds`).
  """
  betas = np.round(np.linspace(0.0, 1.0, 21), 4) if betas is None else np.asarray(betas)
  grid, best = {}, {}
  for name, data in (("calibration", calibration), ("held_out", held_out)):
    out = sweep_beta(data["frames"], data["camera"], data["coords"], data["labels"],
                     betas=betas, rule=rule, capacity=data["capacity"], voxel_size=voxel_size,
                     mask=data["mask"], mesh=mesh, aggregate=aggregate)
    grid[name] = {"miou": out["miou_pooled"], "cross_entropy": out["loss_mean"],
                  "soft_iou": out["soft_iou_loss_pooled"]}
    best[name] = float(betas[int(np.nanargmax(out["miou_pooled"]))])
  tuned, seconds = {}, {}
  for objective in OBJECTIVES:
    start = time.perf_counter()
    tuned[objective] = tune_hparams(
        calibration["frames"], calibration["camera"], calibration["coords"],
        calibration["labels"], rule=rule, init={"beta": init_beta}, steps=steps,
        learning_rate=learning_rate, capacity=calibration["capacity"], voxel_size=voxel_size,
        mask=calibration["mask"], aggregate=aggregate, objective=objective)
    seconds[objective] = time.perf_counter() - start
  evals = evaluate_rules([res.rule for res in tuned.values()], held_out["frames"],
                         held_out["camera"], held_out["coords"], held_out["labels"],
                         capacity=held_out["capacity"], voxel_size=voxel_size,
                         mask=held_out["mask"], mesh=mesh)
  report = {}
  for (objective, res), ev in zip(tuned.items(), evals):
    beta_star = float(res.hparams["beta"])
    report[objective] = {
        "beta_star": beta_star,
        "grid_argmin": {n: float(betas[int(np.nanargmin(g[objective]))])
                        for n, g in grid.items()},
        "spearman": {n: spearman(-g[objective], g["miou"]) for n, g in grid.items()},
        "held_out_miou": float(ev["miou_pooled"]),
        "distance": abs(beta_star - best["held_out"]),
        "regret": float(np.nanmax(grid["held_out"]["miou"]) - ev["miou_pooled"]),
        "losses": res.losses.tolist(), "seconds": seconds[objective]}
  return {"betas": betas, "grid": grid, "best_beta": best, "objectives": report,
          "rule": rule, "aggregate": aggregate, "steps": steps, "init_beta": init_beta,
          "calibration": calibration["names"], "held_out": held_out["names"],
          "source": calibration["source"]}


def format_comparison(result: dict) -> str:
  """A Markdown table of `compare_objectives`."""
  best = result["best_beta"]
  held = result["grid"]["held_out"]["miou"]
  lines = [
      f"rule {result['rule']} ({result['aggregate']}), {len(result['calibration'])} "
      f"calibration / {len(result['held_out'])} held-out sequences, {result['source']}; "
      f"β grid optimum (mIoU): calibration {best['calibration']:.2f}, held-out "
      f"{best['held_out']:.2f} ({100 * np.nanmax(held):.2f} mIoU)", "",
      "| objective | β* (gradient) | grid argmin cal. / held-out | Spearman(−loss, mIoU) cal. / "
      "held-out | held-out mIoU at β* | regret | |β* − best β| |",
      "|---|---|---|---|---|---|---|"]
  for name, r in result["objectives"].items():
    lines.append(
        f"| {name} | {r['beta_star']:.3f} | {r['grid_argmin']['calibration']:.2f} / "
        f"{r['grid_argmin']['held_out']:.2f} | {r['spearman']['calibration']:.2f} / "
        f"{r['spearman']['held_out']:.2f} | {100 * r['held_out_miou']:.2f} | "
        f"{100 * r['regret']:.2f} | {r['distance']:.3f} |")
  return "\n".join(lines)


# --- the protocol: tune on calibration seeds, judge on held-out seeds ----------------------------
def tune_protocol(calibration: dict, held_out: dict, *, rule: str = "D+R",
                  objective: str = DEFAULT_OBJECTIVE, baseline_beta: float = 0.3,
                  steps: int = 40, learning_rate: float = 0.1, aggregate: str = "sum",
                  voxel_size: float = 0.1, num_resamples: int = stats.DEFAULT_RESAMPLES,
                  confidence: float = stats.DEFAULT_CONFIDENCE, seed: int = 0,
                  mesh=None) -> dict:
  """Scalar β*, per-class β* and the paper's β side by side on held-out sequences.

  β is tuned by gradient (`tune_hparams`, `objective`) on the calibration batch, once as one
  scalar and once per class (docs/equations.md §3.7); the three rules are then fused on every
  held-out sequence and scored against GT voxel labels. Intervals are percentile bootstraps over the
  held-out sequences (`stats.bootstrap` of the pooled confusion's mIoU), and the differences to the
  baseline are paired bootstraps on the same resamples (`stats.paired_difference`).

  Args:
    calibration: a batch from `load_sequence_batch` (e.g. layout seeds A).
    held_out: a batch on other layouts (seeds B).
    rule: "R" or "D+R".
    objective: the tuning surrogate (see `tune_hparams`).
    baseline_beta: the paper's β.
    steps: Adam steps per tuning run.
    learning_rate: Adam step size.
    aggregate: pixel aggregation.
    voxel_size: voxel edge (the GT's).
    num_resamples: bootstrap resamples.
    confidence: interval coverage.
    seed: bootstrap seed.
    mesh: shard the evaluations over devices.

  Returns:
    dict with `methods` (name → `beta` (float or list of K), `miou` / `accuracy`
    `stats.Interval` on the held-out sequences, `vs_baseline` (paired Interval of the mIoU
    difference, None for the baseline), `iou` (per class, pooled), `miou_calibration`,
    `miou_per_sequence`), `tuning` (per tuned method: losses, seconds), and the settings.
  """
  check_objective(objective)
  tuned, timing = {}, {}
  for name, per_class in (("scalar β*", False), ("per-class β*", True)):
    start = time.perf_counter()
    tuned[name] = tune_hparams(
        calibration["frames"], calibration["camera"], calibration["coords"],
        calibration["labels"], rule=rule, init={"beta": baseline_beta}, steps=steps,
        learning_rate=learning_rate, capacity=calibration["capacity"], voxel_size=voxel_size,
        mask=calibration["mask"], aggregate=aggregate, objective=objective,
        per_class=per_class)
    timing[name] = time.perf_counter() - start
  baseline = f"β = {baseline_beta:g}"
  rules = {baseline: rules_lib.by_name(rule, beta=baseline_beta, aggregate=aggregate)}
  rules.update({name: res.rule for name, res in tuned.items()})
  scored = {}
  for split, data in (("held_out", held_out), ("calibration", calibration)):
    outs = evaluate_rules(list(rules.values()), data["frames"], data["camera"], data["coords"],
                          data["labels"], capacity=data["capacity"], voxel_size=voxel_size,
                          mask=data["mask"], mesh=mesh)
    scored[split] = dict(zip(rules, outs))
  counts = stats.resample_counts(len(held_out["names"]), num_resamples, seed=seed)
  base_cms = scored["held_out"][baseline]["confusion"]
  methods = {}
  for name, rule_obj in rules.items():
    out = scored["held_out"][name]
    cms = out["confusion"]   # (S, K, K), one per held-out sequence
    beta = np.asarray(rule_obj.hparams["beta"])
    methods[name] = {
        "beta": float(beta) if beta.ndim == 0 else beta.tolist(),
        "miou": stats.bootstrap(cms, stats.miou, counts=counts, confidence=confidence),
        "accuracy": stats.bootstrap(cms, stats.accuracy, counts=counts, confidence=confidence),
        "vs_baseline": (None if name == baseline else stats.paired_difference(
            cms, base_cms, stats.miou, counts=counts, confidence=confidence)),
        "iou": metrics.iou_from_confusion(out["confusion_pooled"]).tolist(),
        "miou_calibration": float(scored["calibration"][name]["miou_pooled"]),
        "miou_per_sequence": [float(m) for m in out["miou"]]}
  return {"methods": methods, "baseline": baseline, "rule": rule, "objective": objective,
          "aggregate": aggregate, "steps": steps, "learning_rate": learning_rate,
          "calibration": calibration["names"], "held_out": held_out["names"],
          "source": calibration["source"], "confidence": confidence,
          "num_resamples": num_resamples,
          "tuning": {name: {"losses": res.losses.tolist(), "seconds": timing[name]}
                     for name, res in tuned.items()}}


def format_protocol(result: dict, class_names: Sequence[str]) -> str:
  """Markdown tables of `tune_protocol`: mIoU with intervals, and per-class β and IoU."""
  pct = lambda iv: f"{100 * iv.estimate:.2f} [{100 * iv.low:.2f}, {100 * iv.high:.2f}]"
  sgn = lambda iv: (f"{100 * iv.estimate:+.2f} [{100 * iv.low:+.2f}, {100 * iv.high:+.2f}]"
                    if iv is not None else "—")
  conf = int(round(100 * result["confidence"]))
  lines = [
      f"rule {result['rule']} ({result['aggregate']}), tuned by {result['objective']} on "
      f"{len(result['calibration'])} calibration sequences, judged on "
      f"{len(result['held_out'])} held-out sequences ({result['source']}); {conf} % bootstrap "
      f"intervals over held-out sequences ({result['num_resamples']} resamples)", "",
      f"| method | β | held-out mIoU | Δ mIoU vs {result['baseline']} (paired) | held-out acc. "
      f"| calibration mIoU |", "|---|---|---|---|---|---|"]
  for name, m in result["methods"].items():
    beta = (f"{m['beta']:.3f}" if isinstance(m["beta"], float)
            else "per class (below)")
    lines.append(f"| {name} | {beta} | {pct(m['miou'])} | {sgn(m['vs_baseline'])} | "
                 f"{pct(m['accuracy'])} | {100 * m['miou_calibration']:.2f} |")
  lines += ["", "| | " + " | ".join(class_names) + " |",
            "|---|" + "---|" * len(class_names)]
  for name, m in result["methods"].items():
    beta = m["beta"] if isinstance(m["beta"], list) else [m["beta"]] * len(class_names)
    lines.append(f"| β ({name}) | " + " | ".join(f"{b:.3f}" for b in beta) + " |")
  for name, m in result["methods"].items():
    lines.append(f"| IoU ({name}) | " + " | ".join(
        "—" if v is None or not np.isfinite(v) else f"{100 * v:.1f}" for v in m["iou"]) + " |")
  return "\n".join(lines)


# --- command line --------------------------------------------------------------------------------
def add_data_args(parser: argparse.ArgumentParser, *, rule_help: str = "robust rule: R, D "
                   "or D+R", layout_seeds: bool = True, calibration: bool = False,
                  validation: bool = False) -> None:
  flags.add_sizes(parser, frames=20, height=60, width=80, samples=False)
  parser.add_argument("--voxel-size", type=float, default=0.1, help="voxel edge in metres")
  parser.add_argument("--rule", default="D+R", help=rule_help)
  parser.add_argument("--aggregate", choices=("sum", "mean"), default="sum",
                      help="a voxel's pixels in one frame: summed (the paper) or one mean "
                           "observation")
  parser.add_argument("--front-end", choices=FRONT_ENDS, default="simulated",
                      help="'shipped': the packaged MC-dropout network, run once per sequence "
                           "and cached (--cache); 'simulated': independent per-pixel errors, "
                           "simulation.simulate_predictions")
  parser.add_argument("--checkpoint", default=None,
                      help="weights for --front-end shipped (default: the packaged ones)")
  flags.add_cache(parser, default=DEFAULT_CACHE_DIR, aliases=("--cache-dir",))
  flags.add_data(parser, calibration=calibration, validation=validation)
  parser.add_argument("--num-samples", type=int, default=8, help="MC samples M")
  parser.add_argument("--shift", type=float, default=1.0, help="test-domain shift in [0, 1]")
  if layout_seeds:
    flags.add_layout_seeds(parser, default=[0], aliases=("--seed",),
                           help_suffix=" (one; default 0)")
  flags.add_mc_seed(parser, what="the MC-dropout keys or the simulated network's draws")
  parser.add_argument("--devices", type=int, default=None,
                      help="shard the sweep over this many devices (default: one)")
  parser.add_argument("--json", default=None, help="write the results as JSON here")


def data_front_end(args):
  """The front end of `--data` sequences without --predictions: `sequences.SIMULATED`, the
  shipped network (--front-end shipped), or None with --predictions."""
  from jaxfusion.lab import sequences  # pylint: disable=import-outside-toplevel
  if args.predictions is not None:
    return None
  if args.front_end == "simulated":
    return sequences.SIMULATED
  return frontend.FrontEnd(args.checkpoint, class_names=None)


def data_options(args, **defaults):
  """`flags.data_options` with the tuning commands' sizes, shift and seeds."""
  seeds = getattr(args, "layout_seeds", None)
  return flags.data_options(args, **{"layout_seed": seeds[0] if seeds else 0,
                                     "shift": args.shift, **defaults})


def front_end_of(args):
  if args.front_end == "simulated":
    return None
  if args.predictions is not None:
    raise ValueError("--predictions and --front-end shipped exclude each other")
  return frontend.FrontEnd(args.checkpoint)


def data_kwargs(args, front_end=None) -> dict:
  return {"num_frames": args.frames, "height": args.height, "width": args.width,
          "voxel_size": args.voxel_size, "predictions": args.predictions,
          "num_samples": args.num_samples, "shift": args.shift, "front_end": front_end,
          "cache_dir": args.cache, "key_seed": args.mc_seed}


def _mesh(args):
  """The devices to shard over: `--devices N`, or every device of every process when the
  command runs as several processes (`--processes`, `--distributed`); None: one device."""
  if args.devices is None and jax.process_count() > 1:
    return batch.make_mesh()
  return None if args.devices in (None, 1) else batch.make_mesh(args.devices)


def _write_json(path: Optional[str], payload: dict) -> None:
  if path:
    reports.write_json(path, payload, indent=2)
    print(f"wrote {path}")


def add_parser(subparsers) -> None:
  """Adds `sweep`, `tune-beta`, `tune-compare` and `tune-protocol`."""
  add_sweep_parser(subparsers)
  add_tune_beta_parser(subparsers)
  add_tune_compare_parser(subparsers)
  add_tune_protocol_parser(subparsers)


def main(args: argparse.Namespace) -> int:
  """Runs the parsed tuning command."""
  return args.func(args)


def add_sweep_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `sweep`: mIoU / accuracy / surrogate losses for a grid of β, as one compiled call."""
  parser = subparsers.add_parser(
      "sweep", help="fuse one synthetic sequence with a grid of β in one compiled call",
      description="Fuses a synthetic sequence with R values of β at once (jax.vmap over the "
                  "stacked rules, optionally sharded over devices) and reports mIoU, accuracy "
                  "and both tuning surrogates (cross-entropy, 1 − soft mIoU) per β. The "
                  "network is simulated, the shipped one (--front-end shipped) or "
                  "precomputed (--predictions).")
  parser.add_argument("--sequence", default="office:0", help="ENV:TRAJECTORY")
  parser.add_argument("--num-betas", type=int, default=32)
  parser.add_argument("--beta-min", type=float, default=0.0)
  parser.add_argument("--beta-max", type=float, default=1.0)
  parser.add_argument("--plot", default=None, help="save a plot of mIoU against β here (PNG)")
  add_data_args(parser)
  flags.add_processes(parser)
  parser.set_defaults(func=sweep_command)
  return parser


def add_tune_beta_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `tune-beta`: fit β (and ε, α₀) on a calibration trajectory, score held-out ones."""
  parser = subparsers.add_parser(
      "tune-beta", help="fit β by gradient descent on a calibration trajectory",
      description="Fits β = sigmoid(u) (and optionally ε = exp(v), α₀ = softplus(w)), one "
                  "value or one per class, with Adam on a surrogate of map quality (the "
                  "cross-entropy by default, or 1 − soft mIoU) of the fused voxel posteriors "
                  "against GT voxel labels of a calibration trajectory, then reports mIoU at "
                  "β* and at a baseline β on held-out trajectories.")
  parser.add_argument("--calibration", default="office:0", help="ENV:TRAJECTORY")
  parser.add_argument("--held-out", default="office:1,office:2,house:0,house:1,house:2",
                      help="comma-separated ENV:TRAJECTORY list")
  parser.add_argument("--steps", type=int, default=40)
  parser.add_argument("--learning-rate", type=float, default=0.1)
  parser.add_argument("--init-beta", type=float, default=0.3)
  parser.add_argument("--baseline-beta", type=float, default=0.3)
  parser.add_argument("--tune", default="beta",
                      help="comma-separated hyperparameters to fit: beta, eps, alpha0")
  parser.add_argument("--objective", choices=OBJECTIVES, default=DEFAULT_OBJECTIVE,
                      help="surrogate to minimise")
  parser.add_argument("--per-class", action="store_true",
                      help="fit one value per class for each tuned hyperparameter")
  parser.add_argument("--stream", action="store_true",
                      help="with --calibration-data: read the calibration sequences from disk a "
                           "chunk at a time and differentiate chunk by chunk (bounded memory, "
                           "the same fit, about 4 reads of the data a step)")
  add_data_args(parser, calibration=True)
  parser.set_defaults(func=tune_beta_command)
  return parser


def _add_protocol_args(parser: argparse.ArgumentParser) -> None:
  parser.add_argument("--envs", nargs="+", choices=("office", "house"),
                      default=["office", "house"])
  parser.add_argument("--trajectories", nargs="+", type=int, choices=(0, 1, 2),
                      default=[0, 1, 2])
  parser.add_argument("--calibration-seeds", nargs="+", type=int, default=[1],
                      help="layout seeds of the calibration sequences (A)")
  parser.add_argument("--held-out-seeds", nargs="+", type=int, default=[2, 3],
                      help="layout seeds of the held-out sequences (B, disjoint from A)")
  parser.add_argument("--steps", type=int, default=40)
  parser.add_argument("--learning-rate", type=float, default=0.1)
  parser.add_argument("--out", default="outputs/tune", help="output folder")
  add_data_args(parser, rule_help="robust rule with β: R or D+R", layout_seeds=False)


def add_tune_compare_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `tune-compare`: which surrogate's optimum tracks the mIoU optimum of a β sweep."""
  parser = subparsers.add_parser(
      "tune-compare", help="compare the tuning objectives against a β sweep's mIoU optimum",
      description="Tunes β by gradient with each objective (soft IoU, cross-entropy) on "
                  "calibration layouts, sweeps a β grid on calibration and held-out layouts, "
                  "and reports where each objective's optimum lands relative to the mIoU "
                  "optimum (writes compare.md/.json/.png under --out).")
  _add_protocol_args(parser)
  parser.add_argument("--init-beta", type=float, default=0.3)
  parser.add_argument("--num-betas", type=int, default=21, help="grid 0..1")
  parser.set_defaults(func=tune_compare_command)
  return parser


def add_tune_protocol_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `tune-protocol`: scalar β*, per-class β* and β = 0.3 on held-out layouts."""
  parser = subparsers.add_parser(
      "tune-protocol", help="tune scalar and per-class β on calibration layouts, judge them "
                            "against β = 0.3 on held-out layouts with bootstrap intervals",
      description="Tunes β (one scalar, and one per class) by gradient on the calibration "
                  "layout seeds, fuses the held-out layout seeds with β = 0.3, β* and the "
                  "per-class β*, and reports held-out mIoU with bootstrap intervals over "
                  "sequences (writes protocol.md/.json and per_class_beta.png under --out).")
  _add_protocol_args(parser)
  parser.add_argument("--objective", choices=OBJECTIVES, default=DEFAULT_OBJECTIVE)
  parser.add_argument("--baseline-beta", type=float, default=0.3)
  parser.add_argument("--resamples", type=int, default=stats.DEFAULT_RESAMPLES,
                      help="bootstrap resamples")
  parser.set_defaults(func=tune_protocol_command)
  return parser


def sweep_command(args) -> int:
  """Runs `jaxfusion sweep`; returns the exit status."""
  specs = flags.data_sets(args, "data")["--data"]
  betas = np.linspace(args.beta_min, args.beta_max, args.num_betas)
  if specs is not None:
    if len(specs) != 1:
      raise ValueError(f"sweep fuses one sequence: give one --data spec; got {len(specs)}")
    if jax.process_count() > 1:
      raise ValueError("sweep --data streams its sequence chunk by chunk in one process; "
                       "--processes / --distributed shard the sweep of an embedded sequence")
    start = time.perf_counter()
    data, out = stream_sweep(specs[0], data_options(args), betas, rule=args.rule,
                             aggregate=args.aggregate, front_end=data_front_end(args))
    seconds = time.perf_counter() - start
  else:
    data = load_calibration_sequence(args.sequence, seed=flags.one_layout_seed(args),
                                     **data_kwargs(args, front_end_of(args)))
    start = time.perf_counter()
    out = sweep_beta(data["frames"], data["camera"], data["gt"]["coords"],
                     data["gt"]["labels"], betas=betas, rule=args.rule,
                     capacity=data["capacity"], voxel_size=args.voxel_size, mesh=_mesh(args),
                     aggregate=args.aggregate)
    seconds = time.perf_counter() - start
  if jax.process_index() != 0:
    return 0   # every process holds the gathered result; process 0 reports it
  best = int(np.nanargmax(out["miou"]))
  print(f"{data['name']} ({data['source']}), rule {args.rule}, aggregate={args.aggregate}: "
        f"{len(betas)} β in one call, {seconds:.1f} s including compilation")
  print("   beta    mIoU     acc   xent  1-softIoU")
  for b, m, a, l, q in zip(out["beta"], out["miou"], out["accuracy"], out["loss"],
                           out["soft_iou_loss"]):
    print(f"  {b:5.3f}  {100 * m:6.2f}  {100 * a:6.2f}  {l:6.3f}  {q:6.4f}")
  print(f"best β = {out['beta'][best]:.3f}: mIoU {100 * out['miou'][best]:.2f}; surrogate "
        f"minima: cross-entropy at β = {out['beta'][int(np.nanargmin(out['loss']))]:.3f}, soft "
        f"IoU at β = {out['beta'][int(np.nanargmin(out['soft_iou_loss']))]:.3f}")
  if args.plot:
    figures.miou_vs_beta(args.plot, out["beta"], out["miou"],
                         title=f"{data['name']}, {args.rule} ({args.aggregate})")
    print(f"wrote {args.plot}")
  _write_json(args.json, {
      "sequence": data["name"], "source": data["source"], "rule": args.rule,
      "aggregate": args.aggregate, "seconds": seconds, "beta": out["beta"].tolist(),
      "miou": out["miou"].tolist(), "accuracy": out["accuracy"].tolist(),
      "loss": out["loss"].tolist(), "soft_iou_loss": out["soft_iou_loss"].tolist()})
  return 0


def _score_held_out(args, result, held_specs, load_held) -> list:
  """mIoU of the baseline β and of the fitted rule on each held-out sequence (printed)."""
  baseline = rules_lib.by_name(args.rule, beta=args.baseline_beta, aggregate=args.aggregate)
  held_out = []
  for spec in held_specs:
    data = load_held(spec)
    base_out, tuned_out = evaluate_rules(
        [baseline, result.rule], data["frames"], data["camera"], data["gt"]["coords"],
        data["gt"]["labels"], capacity=data["capacity"], voxel_size=args.voxel_size,
        mesh=_mesh(args))
    held_out.append({"sequence": data["name"],
                     "miou_baseline": float(base_out["miou"]),
                     "miou_tuned": float(tuned_out["miou"]),
                     "accuracy_baseline": float(base_out["accuracy"]),
                     "accuracy_tuned": float(tuned_out["accuracy"])})
    print(f"  {data['name']:>18}: mIoU {100 * held_out[-1]['miou_baseline']:6.2f} at β = "
          f"{args.baseline_beta:.3f}, {100 * held_out[-1]['miou_tuned']:6.2f} at β*")
  if held_out:
    mean_base = float(np.mean([h["miou_baseline"] for h in held_out]))
    mean_tuned = float(np.mean([h["miou_tuned"] for h in held_out]))
    print(f"  {'mean':>18}: mIoU {100 * mean_base:6.2f} at β = {args.baseline_beta:.3f}, "
          f"{100 * mean_tuned:6.2f} at β*")
  return held_out


def _fmt(value) -> str:
  v = np.asarray(value)
  return f"{float(v):.4g}" if v.ndim == 0 else "[" + ", ".join(f"{x:.3g}" for x in v) + "]"


def tune_beta_command(args) -> int:
  """Runs `jaxfusion tune-beta`; returns the exit status."""
  train = tuple(t.strip() for t in args.tune.split(",") if t.strip())
  given = flags.data_sets(args, "calibration_data", "data")
  if args.stream and given["--calibration-data"] is None:
    raise ValueError("tune-beta --stream reads --calibration-data sequences chunk by chunk; "
                     "give --calibration-data")
  if given["--calibration-data"] is not None or given["--data"] is not None:
    if given["--calibration-data"] is None:
      raise ValueError("tune-beta --data (the held-out sequences) needs --calibration-data "
                       "(the sequences to fit β on)")
    options, front_end = data_options(args), data_front_end(args)
    held_specs = given["--data"] or []
    load_held = lambda spec: load_data_sequence(spec, options, front_end=front_end)
    if args.stream:
      return _tune_beta_streamed(args, given["--calibration-data"], options, front_end, train,
                                 held_specs, load_held)
    cal = load_data_batch(given["--calibration-data"], options, front_end=front_end)
    cal.update(name=", ".join(cal["names"]), gt={"coords": cal["coords"],
                                                  "labels": cal["labels"]})
  else:
    kwargs = data_kwargs(args, front_end_of(args))
    cal = load_calibration_sequence(args.calibration, seed=flags.one_layout_seed(args),
                                    **kwargs)
    held_specs = [s.strip() for s in args.held_out.split(",") if s.strip()]
    load_held = lambda spec: load_calibration_sequence(spec, seed=flags.one_layout_seed(args),
                                                       **kwargs)
  start = time.perf_counter()
  result = tune_hparams(cal["frames"], cal["camera"], cal["gt"]["coords"],
                        cal["gt"]["labels"], rule=args.rule, init={"beta": args.init_beta},
                        train=train, steps=args.steps, learning_rate=args.learning_rate,
                        capacity=cal["capacity"], voxel_size=args.voxel_size,
                        aggregate=args.aggregate, objective=args.objective,
                        per_class=args.per_class, mask=cal.get("mask"))
  seconds = time.perf_counter() - start
  print(f"calibration {cal['name']} ({cal['source']}), rule {args.rule}, "
        f"aggregate={args.aggregate}, objective {args.objective}: {args.steps} Adam steps in "
        f"{seconds:.1f} s")
  print(f"  loss {result.losses[0]:.4f} -> {result.losses[-1]:.4f}; fitted "
        + ", ".join(f"{k} = {_fmt(result.hparams[k])}" for k in train))
  held_out = _score_held_out(args, result, held_specs, load_held)
  _write_json(args.json, {
      "calibration": cal["name"], "source": cal["source"], "rule": args.rule,
      "aggregate": args.aggregate, "objective": args.objective, "per_class": args.per_class,
      "hparams": result.hparams, "losses": result.losses.tolist(),
      "beta_path": result.path.get("beta", np.array([])).tolist(),
      "seconds": seconds, "held_out": held_out})
  return 0


def streamed_calibration(specs, options, *, front_end=None) -> tuple:
  """The calibration sequences of `--calibration-data` for `tune_chunks`: `(read_chunk,
  num_chunks, chunk_size, camera, gts, names, num_classes)`, each sequence streamed from disk
  (`lab.sequences.Streamed`; GT in a first pass, chunk k read on demand)."""
  from jaxfusion.lab import sequences  # pylint: disable=import-outside-toplevel
  items = [sequences.Streamed(s, options, front_end=front_end) for s in specs]
  cameras = {tuple(float(c) for c in i.camera) for i in items}
  sizes = {tuple(i.image_size) for i in items}
  if len(cameras) != 1 or len(sizes) != 1:
    raise ValueError("the calibration sequences must share one camera and image size")
  classes = {i.class_names for i in items}
  if len(classes) != 1:
    raise ValueError("the calibration sequences must share one label space")
  gts = [i.gt() for i in items]
  size = max(i.chunk_size for i in items)
  h, w = items[0].image_size
  k = len(items[0].class_names)

  def read_chunk(b, j):
    got = items[b].chunk(j)
    if got is None:          # no frame of this chunk is readable: a frame that touches nothing
      return fusion.Frame(np.zeros((1, h, w), np.float32), np.eye(4, dtype=np.float32)[None],
                          np.full((1, h, w, k), 1.0 / k, np.float32),
                          np.zeros((1, h, w, k), np.float32))
    return frames_of(*got, rgb=False)

  return (read_chunk, [i.num_chunks for i in items], size, items[0].camera, gts,
          [i.name for i in items], k)


def _tune_beta_streamed(args, specs, options, front_end, train, held_specs, load_held) -> int:
  """`tune-beta --stream`: β fitted through the calibration sequences read chunk by chunk
  (`tune_chunks.tune_hparams_chunks`), then scored on the held-out ones."""
  from tqdm.auto import tqdm  # pylint: disable=import-outside-toplevel
  from jaxfusion import tune_chunks  # pylint: disable=import-outside-toplevel
  read, counts, size, camera, gts, names, k = streamed_calibration(specs, options,
                                                                   front_end=front_end)
  bar = tqdm(total=args.steps, desc="tune-beta (streamed)", unit="step")
  start = time.perf_counter()
  result = tune_chunks.tune_hparams_chunks(
      read, counts, camera, gts, num_classes=k, rule=args.rule, init={"beta": args.init_beta},
      train=train, steps=args.steps, learning_rate=args.learning_rate,
      capacity=max(data_capacity(g) for g in gts), voxel_size=args.voxel_size,
      aggregate=args.aggregate, objective=args.objective, per_class=args.per_class,
      chunk_size=size, progress=lambda step, loss: (bar.update(1), bar.set_postfix(
          loss=f"{loss:.4f}")))
  bar.close()
  seconds = time.perf_counter() - start
  print(f"calibration {', '.join(names)} (streamed in chunks of {size} frames), rule "
        f"{args.rule}, objective {args.objective}: {args.steps} Adam steps in {seconds:.1f} s")
  print(f"  loss {result.losses[0]:.4f} -> {result.losses[-1]:.4f}; fitted "
        + ", ".join(f"{key} = {_fmt(result.hparams[key])}" for key in train))
  held_out = _score_held_out(args, result, held_specs, load_held)
  _write_json(args.json, {
      "calibration": names, "streamed": True, "rule": args.rule, "aggregate": args.aggregate,
      "objective": args.objective, "per_class": args.per_class, "hparams": result.hparams,
      "losses": result.losses.tolist(), "seconds": seconds, "held_out": held_out})
  return 0


def _protocol_batches(args) -> tuple:
  overlap = set(args.calibration_seeds) & set(args.held_out_seeds)
  if overlap:
    raise ValueError(f"calibration and held-out layout seeds must be disjoint; both have "
                     f"{sorted(overlap)}")
  kwargs = data_kwargs(args, front_end_of(args))
  units = lambda seeds: [(e, t, s) for s in seeds for e in args.envs for t in args.trajectories]
  return (load_sequence_batch(units(args.calibration_seeds), **kwargs),
          load_sequence_batch(units(args.held_out_seeds), **kwargs))


def tune_compare_command(args) -> int:
  """Runs `jaxfusion tune-compare`; returns the exit status."""
  import os  # pylint: disable=import-outside-toplevel
  cal, held = _protocol_batches(args)
  result = compare_objectives(cal, held, rule=args.rule,
                              betas=np.round(np.linspace(0.0, 1.0, args.num_betas), 4),
                              steps=args.steps, learning_rate=args.learning_rate,
                              init_beta=args.init_beta, aggregate=args.aggregate,
                              voxel_size=args.voxel_size, mesh=_mesh(args))
  table = format_comparison(result)
  print(table)
  os.makedirs(args.out, exist_ok=True)
  reports.write_text(os.path.join(args.out, "compare.md"), table + "\n")
  figures.objective_comparison(os.path.join(args.out, "compare.png"), result)
  _write_json(args.json or os.path.join(args.out, "compare.json"), result)
  print(f"wrote {args.out}/compare.md, compare.png")
  return 0


def tune_protocol_command(args) -> int:
  """Runs `jaxfusion tune-protocol`; returns the exit status."""
  import os  # pylint: disable=import-outside-toplevel
  from jaxfusion import datasets  # pylint: disable=import-outside-toplevel
  cal, held = _protocol_batches(args)
  result = tune_protocol(cal, held, rule=args.rule, objective=args.objective,
                         baseline_beta=args.baseline_beta, steps=args.steps,
                         learning_rate=args.learning_rate, aggregate=args.aggregate,
                         voxel_size=args.voxel_size, num_resamples=args.resamples,
                         mesh=_mesh(args))
  names = list(datasets.CLASS_NAMES)[:cal["num_classes"]]
  table = format_protocol(result, names)
  print(table)
  os.makedirs(args.out, exist_ok=True)
  reports.write_text(os.path.join(args.out, "protocol.md"), table + "\n")
  figures.per_class_beta(os.path.join(args.out, "per_class_beta.png"), result, names)
  _write_json(args.json or os.path.join(args.out, "protocol.json"),
              dict(result, class_names=names, settings={
                  "frames": args.frames, "height": args.height, "width": args.width,
                  "num_samples": args.num_samples, "shift": args.shift,
                  "front_end": args.front_end, "voxel_size": args.voxel_size}))
  print(f"wrote {args.out}/protocol.md, per_class_beta.png")
  return 0
