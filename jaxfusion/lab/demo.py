"""The paper's experiment on the embedded world: for each environment × trajectory, run the
front end once (MC dropout for the robust rules, dropout off for the baselines), cache its
outputs, fuse with all six rules, evaluate against GT voxel labels, and aggregate over
trajectories (confusion matrices are summed, then IoU is computed) — Tables I/II's layout.
"""

import csv
import dataclasses
import hashlib
import io as _io
import json
import os
from typing import Optional, Sequence

import jax
import numpy as np
from tqdm.auto import tqdm

import jaxfusion as jf
from jaxfusion.lab import figures
from jaxfusion import io
from jaxfusion import metrics

# The paper's setting: robust rules read the MC-dropout moments, baselines one dropout-off pass.
ROBUST_RULES = ("robust_r", "robust_d", "robust_dr")
CACHE_VERSION = 2


@dataclasses.dataclass(frozen=True)
class ExperimentConfig:
  """What to run. The defaults are the full experiment; `quick()` is a ~2-minute version."""
  envs: tuple = ("office", "house")
  trajectories: tuple = (0, 1, 2)
  rules: tuple = tuple(jf.rules.PAPER_RULES)
  num_frames: int = 40
  height: int = 120
  width: int = 160
  num_samples: int = 32
  domain: str = "test"
  shift: float = 1.0
  scene_seed: int = 0
  seed: int = 0
  voxel_size: float = 0.1
  capacity: int = 2**17
  beta: float = 0.3
  aggregate: str = "sum"

  @classmethod
  def quick(cls, **overrides) -> "ExperimentConfig":
    base = dict(envs=("office",), trajectories=(0,), num_frames=20, height=90, width=120,
                num_samples=8)
    base.update(overrides)
    return cls(**base)

  def make_rule(self, name: str):
    kwargs = {"aggregate": self.aggregate}
    if name in ROBUST_RULES:
      kwargs["beta"] = self.beta
    return jf.rules.by_name(name, **kwargs)


def _file_digest(path: str) -> str:
  h = hashlib.sha256()
  with open(path, "rb") as f:
    for chunk in iter(lambda: f.read(1 << 20), b""):
      h.update(chunk)
  return h.hexdigest()[:16]


class FrontEnd:
  """The shipped MC-dropout network as the experiment's observation source."""

  def __init__(self, checkpoint: Optional[str] = None):
    import jaxfusion_models as models   # application layer: the engine never imports models
    self._models = models
    path = checkpoint or models.PRETRAINED_PATH
    from jaxfusion import datasets
    self.model = models.load(path, class_names=datasets.CLASS_NAMES)
    self.model_id = _file_digest(str(path))

  def predict(self, rgb: np.ndarray, *, num_samples: int, key) -> tuple:
    """`(T, H, W, 3) uint8` → deterministic probs, MC mean, MC var, each `(T, H, W, K)`."""
    det, mean, var = [], [], []
    for t in tqdm(range(len(rgb)), desc="front end", leave=False):
      det.append(np.asarray(self._models.deterministic_probs(
          self.model.graphdef, self.model.params, rgb[t])))
      samples = self._models.mc_samples(self.model.graphdef, self.model.params,
                                        jax.random.fold_in(key, t), rgb[t],
                                        num_samples=num_samples)
      m, v = jf.mc_moments(samples)
      mean.append(np.asarray(m))
      var.append(np.asarray(v))
    return np.stack(det), np.stack(mean), np.stack(var)


def _cache_path(cache_dir, model_id, seq_id):
  return os.path.join(cache_dir, f"{seq_id}__model-{model_id}.npz")


def cached_predictions(front_end: FrontEnd, sequence, config: ExperimentConfig, cache_dir: str
                       ) -> dict:
  """The front end's outputs for a sequence, computed once and cached (write then rename).

  A cache written for another model, sequence or M is never used: the file name carries the
  model's digest, the layout seed, shift, resolution, frame count, M, the MC seed and a digest
  of the rendered images (so any change of the sensing settings or of the renderer is a new
  entry), and the metadata inside is checked.
  """
  rgb_digest = hashlib.sha256(np.ascontiguousarray(sequence.rgb).tobytes()).hexdigest()[:12]
  seq_id = (f"{sequence.name}_s{config.scene_seed}_{config.height}x{config.width}"
            f"_T{len(sequence)}_M{config.num_samples}_seed{config.seed}_shift{config.shift}"
            f"_rgb{rgb_digest}")
  path = _cache_path(cache_dir, front_end.model_id, seq_id)
  meta = {"version": CACHE_VERSION, "model": front_end.model_id, "sequence": seq_id}
  if os.path.exists(path):
    try:
      with np.load(path) as data:
        stored = json.loads(bytes(data["meta"]).decode())
        if stored == meta:
          return {k: data[k] for k in ("det", "mean", "var")}
      tqdm.write(f"cache {path} was made for {stored}; recomputing")
    except (OSError, ValueError, KeyError):
      tqdm.write(f"cache {path} is unreadable; recomputing")
  det, mean, var = front_end.predict(sequence.rgb, num_samples=config.num_samples,
                                     key=jax.random.PRNGKey(config.seed))

  def write(tmp):
    with open(tmp, "wb") as f:
      np.savez(f, det=det, mean=mean, var=var,
               meta=np.frombuffer(json.dumps(meta).encode(), np.uint8))

  io.atomic_write(path, write)
  return {"det": det, "mean": mean, "var": var}


def fuse_with_rule(sequence, predictions: dict, rule, config: ExperimentConfig):
  """Fuses a whole sequence with one rule; returns the final MapState."""
  num_classes = predictions["mean"].shape[-1]
  state = jf.init_map(capacity=config.capacity, num_classes=num_classes,
                      voxel_size=config.voxel_size, rule=rule)
  robust = rule.name in ROBUST_RULES
  probs = predictions["mean"] if robust else predictions["det"]
  for t in tqdm(range(len(sequence)), desc=jf.rules.display_name(rule), leave=False):
    frame = jf.Frame(sequence.depth[t], sequence.T_world_cam[t], probs[t],
                     predictions["var"][t] if robust else None)
    state = jf.fuse_frame(state, frame, sequence.camera, rule)
  return state


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


def run_experiment(config: ExperimentConfig, out_dir: str, *, cache_dir: Optional[str] = None,
                   checkpoint: Optional[str] = None) -> dict:
  """Runs the whole experiment and writes the table (Markdown, CSV, JSON), maps and figures.

  Returns:
    dict with `table` (Markdown), `results` (per scope → per method), `files` (what was
    written), `unmatched` (per sequence: voxels only in the map / only in GT).
  """
  from jaxfusion import datasets
  os.makedirs(out_dir, exist_ok=True)
  cache_dir = cache_dir or os.path.join(out_dir, "cache")
  front_end = FrontEnd(checkpoint)
  class_names = list(datasets.CLASS_NAMES)
  colors = np.asarray(datasets.CLASS_COLORS, np.uint8)
  k = len(class_names)
  rules = {name: config.make_rule(name) for name in config.rules}
  display = {name: jf.rules.display_name(rule) for name, rule in rules.items()}
  confusions = {"all": {display[n]: np.zeros((k, k), np.int64) for n in rules}}
  unmatched, files = {}, []
  runs = [(e, t) for e in config.envs for t in config.trajectories]
  for env, traj in tqdm(runs, desc="sequences"):
    seq = datasets.make_sequence(env, traj, domain=config.domain, num_frames=config.num_frames,
                                 height=config.height, width=config.width,
                                 seed=config.scene_seed, shift=config.shift)
    gt = datasets.gt_voxel_labels(seq, voxel_size=config.voxel_size, capacity=config.capacity)
    preds = cached_predictions(front_end, seq, config, cache_dir)
    confusions.setdefault(env, {display[n]: np.zeros((k, k), np.int64) for n in rules})
    views = {"Ground truth": gt}
    for name, rule in rules.items():
      state = fuse_with_rule(seq, preds, rule, config)
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
                    mode="cubes" if traj == config.trajectories[0] else "points")
      files += [stem + ".npz", stem + ".ply"]
      views[display[name]] = voxels
    gt_npz = os.path.join(out_dir, "maps", f"{seq.name}_gt.npz")   # for `jaxfusion view`
    io.atomic_write(gt_npz, lambda tmp, gt=gt: _save_npz(tmp, gt))
    files.append(gt_npz)
    gt_path = os.path.join(out_dir, "maps", f"{seq.name}_gt.ply")
    io.export_ply(gt_path, gt, voxel_size=config.voxel_size, colors=colors,
                  mode="cubes" if traj == config.trajectories[0] else "points")
    files.append(gt_path)
    if traj == config.trajectories[0]:
      shown = {t: v for t, v in views.items() if t in ("Ground truth", "Bayesian", "D+R")}
      path = os.path.join(out_dir, f"maps_{seq.name}.png")
      figures.map_views(path, shown, voxel_size=config.voxel_size, colors=colors)
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
  io.atomic_write(paths[0], lambda tmp: open(tmp, "w").write(table + "\n"))
  buf = _io.StringIO()
  w = csv.writer(buf)
  w.writerow(["scope", "method"] + list(class_names) + ["mIoU", "Acc"])
  for scope, res in results.items():
    for method, r in res.items():
      w.writerow([scope, method] + [f"{v:.4f}" for v in r["iou"]] +
                 [f"{r['miou']:.4f}", f"{r['accuracy']:.4f}"])
  io.atomic_write(paths[1], lambda tmp: open(tmp, "w").write(buf.getvalue()))
  payload = {
      "config": dataclasses.asdict(config),
      "class_names": list(class_names),
      "results": {scope: {m: {"iou": [None if np.isnan(v) else float(v) for v in r["iou"]],
                              "miou": r["miou"], "accuracy": r["accuracy"],
                              "confusion": r["confusion"].tolist()}
                          for m, r in res.items()} for scope, res in results.items()},
      "unmatched": unmatched,
  }
  io.atomic_write(paths[2], lambda tmp: open(tmp, "w").write(json.dumps(payload, indent=1)))
  return paths
