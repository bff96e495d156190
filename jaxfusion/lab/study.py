"""The fusion experiment as a study with statistics: `jaxfusion study`.

Grid: the six rules × domain shifts × layout seeds × environments × trajectories. Each *unit*
(layout seed, environment, trajectory) is rendered at every shift with `make_sequence`'s
default sensing; the front end runs once per rendered sequence (MC dropout with M samples for
the robust rules, one dropout-off pass for the baselines, as in `jaxfusion demo`) and is cached
on disk (`frontend.cached_predictions`, keyed by the model's digest, shift, layout seed,
resolution, frames, M and a digest of the rendered images). Then every sequence is fused with
all rules and with the oracle, and scored against GT voxel labels as the demo does.

Definitions (per shift; a voxel's GT label y is the majority of its GT pixel labels; the
observations, headroom categories and α are computed by the library's `jaxfusion.observations`):

* **Pixel observation**: a pixel with valid depth whose voxel (the engine's key) is a GT voxel;
  it *votes* for the argmax of the front end's MC-mean probabilities (what the robust rules
  read). It is **right** when that class equals y of its voxel, **wrong** otherwise.
* **Scored voxels**: GT voxels with at least one pixel observation (the voxels every map has).
* **Voxel headroom**: with n_k the votes for class k over the whole sequence, a scored voxel is
  *mostly right* when n_y > max_{k≠y} n_k (a plurality vote is right), *outvoted right* when
  0 < n_y ≤ max_{k≠y} n_k (some observations are right but are outvoted or tied: only here can
  a better weighting of the observations win), and *never right* when n_y = 0.
* **Recovered** (per rule): the share of outvoted-right voxels whose map label is y. The
  accuracies on mostly-right and never-right voxels are reported too.
* **Oracle**: an error detector that knows which observations are wrong: the depth of every
  wrong pixel (and of pixels outside GT voxels) is set to invalid and the MC means of the right
  pixels are fused with the Bayesian rule; voxels that keep no observation (never right) take
  the Bayesian map's label. Every observation fused for a voxel has argmax y and the Bayesian
  posterior is the normalised sum of their log-probabilities, so the oracle labels every voxel
  with a right observation correctly: its confusion dominates the Bayesian map voxel by voxel,
  and it bounds every rule that cannot win a voxel no observation votes right for.
* **α** of a pixel: `−log(clip(var_c, 0, 0.25) + ε)` of its predicted class c (the D rules'
  weight, ε = 1e-12), histogrammed for right and wrong pixel observations; AUROC is
  P(α_right > α_wrong) + ½ P(same 0.1-nat bin), from the histograms.
* **Intervals**: percentile bootstrap over sequences (`stats`): sequences are resampled with
  replacement, confusion matrices (and voxel / pixel counts) are summed over the resample and
  mIoU, accuracy or the share is computed from the sums. One set of resamples is shared by all
  methods and shifts, so a paired difference (e.g. D+R − Bayes) is evaluated on the same
  resamples for both methods.

Outputs under OUT: `study.md`, `study.csv` (long format), `study.json` (summaries, per-sequence
raw counts, config), `timing.json` (seconds per stage, sequence and process),
`miou_vs_shift.png`, `differences_vs_shift.png`, `headroom.png`, `alpha_hist.png`.

**Several processes** (`--processes N` on one machine, `--distributed` on a cluster;
`jaxfusion.distributed`): each process renders, predicts and fuses every N-th sequence of the
grid, the per-sequence counts are gathered in grid order through JAX's collectives, and process
0 computes the statistics and writes the outputs. What the study reports does not depend on N:
study.json, the tables and the figures are the same bytes as one process writes.

Shape legend: S sequences, T frames, H×W pixels, N = H·W, K classes, G GT voxels, P pixel
observations, B bootstrap resamples.
"""

import argparse
import csv
import dataclasses
import io as _io
import os
import time
from typing import Optional

import numpy as np
from tqdm.auto import tqdm

import jaxfusion as jf
from jaxfusion import distributed
from jaxfusion.lab import config as config_lib
from jaxfusion.lab import flags
from jaxfusion.lab import frontend
from jaxfusion.lab import reports
from jaxfusion.lab import figures
from jaxfusion import io
from jaxfusion import learn
from jaxfusion import metrics
from jaxfusion.lab import stats
from jaxfusion.datasets.classes import CLASS_NAMES
# The analyses of pixel observations are general and live in the library
# (`jaxfusion.observations`); their names stay importable from here.
from jaxfusion.observations import HEADROOM
from jaxfusion.observations import alpha_of_prediction
from jaxfusion.observations import classify_voxels  # pylint: disable=unused-import
from jaxfusion.observations import classify_votes
from jaxfusion.observations import voxel_votes
from jaxfusion.observations import feature_histograms
from jaxfusion.observations import pixel_observations

ORACLE = "oracle"
# The learned rule (`rules.learned` with `StudyConfig.learned` parameters), a seventh row.
LEARNED = "learned"
# GLFS (`rules.glfs` with `StudyConfig.glfs` parameters), the published learned peer.
GLFS = "glfs"
# Other fitted learned rules (an ablation) are named "learned:<tag>".
VARIANT_PREFIX = "learned:"
# Paired comparisons (A, B) reported as A − B, in this order (those whose rules are run).
COMPARISONS = (("robust_dr", "bayes"), ("robust_dr", "sum_probs"), ("robust_r", "bayes"),
               ("robust_d", "bayes"), (LEARNED, "bayes"), (LEARNED, "robust_dr"),
               (LEARNED, "robust_r"), (LEARNED, "robust_d"), (GLFS, "bayes"), (LEARNED, GLFS),
               (ORACLE, "bayes"))
# α bins: 0.1 nat from 0 to 28 (α ≤ −log 1e-12 ≈ 27.6).
ALPHA_EDGES = np.linspace(0.0, 28.0, 281)
# The demo's layout seed; the study's default seeds avoid it.
DEMO_SEED = config_lib.RunConfig.layout_seeds[0]


def _study_run(**overrides) -> config_lib.RunConfig:
  base = dict(layout_seeds=(1, 2, 3), shifts=(0.0, 0.25, 0.5, 0.75, 1.0), num_frames=30,
              height=96, width=128, num_samples=16)
  base.update(overrides)
  return config_lib.RunConfig(**base)


@dataclasses.dataclass(frozen=True)
class StudyConfig:
  """What the study runs: a grid of runs (`RunConfig`) and the statistics over it.

  The defaults are the full study; `quick()` a ≤ 3-minute version.

  Attributes:
    run: the grid — layout seeds (the demo uses 0; the study's defaults are others), shifts,
      environments, trajectories, rules (must include "bayes": the oracle's fallback and the
      reference of the comparisons), sizes, M (≥ 2: the robust rules need a variance), β,
      aggregation, voxel size, capacity and the MC seed.
    num_resamples: bootstrap resamples B.
    confidence: interval coverage.
    bootstrap_seed: seed of the bootstrap resamples.
    learned: parameters of `rules.learned` (a dict, e.g. `learn.load_params` of a `learn-rule`
      output): the learned rule is fused on the MC mean and variance as a seventh row; None:
      the six paper rules only.
    learned_source: where `learned` came from (a path), for the report.
    glfs: parameters of `rules.glfs` (a dict: `table`, edges), fused on the MC mean with the
      frame's depth and incidence as a row; None: no GLFS row.
    glfs_source: where `glfs` came from.
    variants: `((tag, params), …)`: more learned rules (e.g. an ablation by feature group),
      and `(tag, params, "family")` members of the rule family (docs/equations.md §3.11),
      each a row "learned:<tag>" compared with Bayes and with the learned row.
    data: the specs of a researcher's sequences (`--data`, strings); empty: the embedded grid
      of `run`. With data, the sequences form one group ("data") instead of one per shift.
    class_names: the map's classes (default the embedded world's).
  """
  run: config_lib.RunConfig = dataclasses.field(default_factory=_study_run)
  num_resamples: int = stats.DEFAULT_RESAMPLES
  confidence: float = stats.DEFAULT_CONFIDENCE
  bootstrap_seed: int = 0
  learned: Optional[dict] = None
  learned_source: Optional[str] = None
  glfs: Optional[dict] = None
  glfs_source: Optional[str] = None
  variants: tuple = ()
  data: tuple = ()
  class_names: tuple = CLASS_NAMES

  @property
  def fitted(self) -> dict:
    """Method name → FusionRule of every fitted row (learned, GLFS, variants), in order."""
    out = {}
    aggregate = self.run.aggregate
    if self.learned is not None:
      out[LEARNED] = jf.rules.learned(self.learned, aggregate=aggregate)
    if self.glfs is not None:
      out[GLFS] = jf.rules.glfs(**self.glfs, aggregate=aggregate)
    for variant in self.variants:
      tag, params = variant[:2]
      out[VARIANT_PREFIX + tag] = learn.rule_of(flags.variant_family(variant), params,
                                                aggregate=aggregate)
    return out

  @property
  def methods(self) -> list:
    """The rules' names in table order, then the fitted rows (when given) and `ORACLE`."""
    fitted = [LEARNED] if self.learned is not None else []
    fitted += [GLFS] if self.glfs is not None else []
    fitted += [VARIANT_PREFIX + v[0] for v in self.variants]
    return list(self.run.rules) + fitted + [ORACLE]

  @property
  def comparisons(self) -> list:
    """`COMPARISONS`, then each variant against Bayes and the learned row against it (a member
    of the rule family against GLFS instead, whose table it starts from)."""
    extra = []
    for variant in self.variants:
      name = VARIANT_PREFIX + variant[0]
      if flags.variant_family(variant) == "family":
        extra += [(name, "bayes")] + ([(name, GLFS)] if self.glfs is not None else [])
      else:
        extra += [(name, "bayes"), (LEARNED, name)]
    return list(COMPARISONS[:-1]) + extra + [COMPARISONS[-1]]

  @classmethod
  def quick(cls, **overrides) -> "StudyConfig":
    """One seed, both environments, one trajectory, three shifts, short small sequences."""
    run = dict(layout_seeds=(1,), trajectories=(0,), shifts=(0.0, 0.5, 1.0), num_frames=12,
               height=60, width=80, num_samples=8)
    run.update(overrides.pop("run", {}))
    return cls(run=_study_run(**run), **overrides)

  @classmethod
  def of(cls, quick: bool = False, *, num_resamples=None, confidence=None, learned=None,
         learned_source=None, glfs=None, glfs_source=None, variants=None,
         **run) -> "StudyConfig":
    """The full (or quick) study with some run fields and statistics replaced (None: keep)."""
    run = {k: v for k, v in run.items() if v is not None}
    stats_overrides = {k: v for k, v in (("num_resamples", num_resamples),
                                         ("confidence", confidence), ("learned", learned),
                                         ("learned_source", learned_source), ("glfs", glfs),
                                         ("glfs_source", glfs_source),
                                         ("variants", variants)) if v is not None}
    if quick:
      return cls.quick(run=run, **stats_overrides)
    return cls(run=_study_run(**run), **stats_overrides)

  def validate(self) -> "StudyConfig":
    """Raises ValueError for an unusable configuration; returns self."""
    self.run.validate(min_samples=2)
    if "bayes" not in self.run.rules:
      raise ValueError(f"rules must include 'bayes'; got {self.run.rules}")
    if int(self.num_resamples) < 1:
      raise ValueError(f"num_resamples must be at least 1; got {self.num_resamples}")
    if not 0.0 < self.confidence < 1.0:
      raise ValueError(f"confidence must lie in (0, 1); got {self.confidence}")
    return self


# --- per-sequence analysis ---------------------------------------------------------------------
def _calibration(voxels, gt_coords, gt_labels) -> np.ndarray:
  """`metrics.calibration_bins` of the map's posteriors at the GT voxels it holds."""
  map_index, gt_index = metrics.match_voxels(voxels["coords"], gt_coords)
  return metrics.calibration_bins(np.asarray(voxels["posterior"])[map_index],
                                  gt_labels[gt_index])


def _labels_at(voxels, gt_coords) -> np.ndarray:
  """`(G,)` map label of each GT voxel, −1 where the map does not hold it."""
  out = np.full(len(gt_coords), -1, np.int64)
  map_index, gt_index = metrics.match_voxels(voxels["coords"], gt_coords)
  out[gt_index] = np.asarray(voxels["labels"])[map_index]
  return out


def _check_predictions(sequence, predictions: dict) -> None:
  missing = [k for k in ("det", "mean", "var") if k not in predictions]
  if missing:
    raise ValueError(f"predictions need 'det', 'mean' and 'var'; missing {missing}")
  shape = np.shape(sequence.depth)
  for k in ("det", "mean", "var"):
    if np.ndim(predictions[k]) != 4 or np.shape(predictions[k])[:3] != shape:
      raise ValueError(f"predictions[{k!r}] must be (T, H, W, K) with (T, H, W) = {shape}; got "
                       f"{np.shape(predictions[k])}")


class SequenceAnalysis:
  """What the study counts for one sequence, accumulated chunk by chunk (`add`), so that a
  long sequence never has to be held whole; `result()` is `analyze_sequence`'s dict.

  Each rule's map (and the oracle's) is carried from chunk to chunk; the pixel votes per GT
  voxel, the α and feature histograms and the pixel counts are summed. Fed the whole sequence
  as one chunk it computes exactly what it always has.

  Args:
    gt: GT voxel labels (`coords (G, 3)`, `labels (G,)`).
    config: the study's configuration.
    num_classes: K.
    grow: maps that grow before they fill (`jf.Mapper`, for data of unknown extent) instead
      of maps of `config.run.capacity` slots.
  """

  def __init__(self, gt: dict, config: StudyConfig, num_classes: int, *, grow: bool = False):
    self.gt, self.config, self.k, self.grow = gt, config, int(num_classes), grow
    self.gt_coords = np.asarray(gt["coords"])
    self.gt_labels = np.asarray(gt["labels"], np.int64)
    self.votes = np.zeros((len(self.gt_labels), self.k), np.int64)
    self.alpha_hist = np.zeros((2, len(ALPHA_EDGES) - 1), np.int64)
    self.features, self.right, self.wrong = None, 0, 0
    self.rules = {name: config.run.make_rule(name) for name in config.run.rules}
    self.rules.update(config.fitted)
    self.oracle_rule = config.run.make_rule("bayes")
    self.maps = {}

  def _fuse(self, key, rule, depth, poses, camera, probs, var, rgb=None):
    frames = jf.Frame(np.asarray(depth, np.float32), np.asarray(poses, np.float32), probs,
                      None if var is None else var, rgb if rule.context else None)
    if key not in self.maps:
      if self.grow:
        self.maps[key] = jf.Mapper(rule, num_classes=self.k, voxel_size=self.config.run.voxel_size,
                                   capacity=self.config.run.capacity)
      else:
        self.maps[key] = jf.init_map(capacity=self.config.run.capacity, num_classes=self.k,
                                     voxel_size=self.config.run.voxel_size, rule=rule)
    if self.grow:
      self.maps[key].fuse_sequence(frames, camera)
    else:
      self.maps[key] = jf.fuse_sequence(self.maps[key], frames, camera, rule)

  def add(self, sequence, predictions: dict) -> None:
    """Adds a chunk of frames (`depth`, `T_world_cam`, `camera`, `rgb`) and its predictions
    (`det`, `mean`, `var`, each `(t, H, W, K)`)."""
    _check_predictions(sequence, predictions)
    k, config = self.k, self.config
    if predictions["mean"].shape[-1] != k:
      raise ValueError(f"predictions have {predictions['mean'].shape[-1]} classes, not {k}")
    obs = pixel_observations(sequence.depth, sequence.T_world_cam, sequence.camera,
                             predictions["mean"], self.gt_coords,
                             voxel_size=config.run.voxel_size)
    observed = obs["gt_index"] >= 0
    right = observed & (obs["pred"] == self.gt_labels[np.maximum(obs["gt_index"], 0)])
    self.votes += voxel_votes(obs["gt_index"], obs["pred"], len(self.gt_labels), k)
    alpha = alpha_of_prediction(predictions["var"].reshape(right.shape + (k,)), obs["pred"])
    self.alpha_hist += np.stack([np.histogram(alpha[right], ALPHA_EDGES)[0],
                                 np.histogram(alpha[observed & ~right], ALPHA_EDGES)[0]]
                                ).astype(np.int64)
    self.right += int(right.sum())
    self.wrong += int((observed & ~right).sum())
    rgb = getattr(sequence, "rgb", None)
    for name, rule in self.rules.items():
      paper = name in config.run.rules
      robust = name in config_lib.ROBUST_RULES
      probs = predictions["mean"] if (robust or not paper) else predictions["det"]
      var = (predictions["var"] if robust else None) if paper else (
          predictions["var"] if rule.requires_var else None)
      self._fuse(name, rule, sequence.depth, sequence.T_world_cam, sequence.camera, probs, var,
                 None if paper else rgb)
    features = feature_histograms(sequence.depth, predictions["mean"], predictions["var"], rgb,
                                  sequence.camera, right, observed)
    self.features = features if self.features is None else {
        n: self.features[n] + v for n, v in features.items()}
    # The oracle: only right observations, fused with the Bayesian rule on the MC mean.
    masked = np.where(right.reshape(sequence.depth.shape), sequence.depth, 0.0
                      ).astype(np.float32)
    self._fuse(ORACLE, self.oracle_rule, masked, sequence.T_world_cam, sequence.camera,
               predictions["mean"], None)

  def _voxels(self, key) -> dict:
    state = self.maps[key].state if self.grow else self.maps[key]
    return jf.read_map(state)

  def result(self) -> dict:
    """The counts of `analyze_sequence`."""
    if not self.maps:
      raise ValueError("no frames were added")
    k, gt, gt_coords, gt_labels = self.k, self.gt, self.gt_coords, self.gt_labels
    category = classify_votes(gt_labels, self.votes)
    headroom = np.array([(category == c).sum() for c in range(3)], np.int64)
    confusion, correct, labels_at, calibration = {}, {}, {}, {}
    result_bayes = None
    for name in self.rules:
      voxels = self._voxels(name)
      ev = metrics.evaluate_map(voxels, gt, k)
      confusion[name] = ev["confusion"]
      labels_at[name] = _labels_at(voxels, gt_coords)
      calibration[name] = _calibration(voxels, gt_coords, gt_labels)
      if name == "bayes":
        result_bayes = ev
    oracle_at = _labels_at(self._voxels(ORACLE), gt_coords)
    in_bayes = labels_at["bayes"] >= 0
    labels_at[ORACLE] = np.where(oracle_at >= 0, oracle_at, labels_at["bayes"])
    confusion[ORACLE] = metrics.confusion_matrix(gt_labels[in_bayes],
                                                 labels_at[ORACLE][in_bayes], k)
    for name, labels in labels_at.items():
      hit = labels == gt_labels
      correct[name] = np.array([(hit & (category == c)).sum() for c in range(3)], np.int64)
    return {"confusion": confusion, "correct": correct, "headroom": headroom,
            "alpha_hist": self.alpha_hist, "feature_hist": self.features,
            "calibration": calibration, "pixels": {"right": self.right, "wrong": self.wrong},
            "matched": result_bayes["matched"], "map_only": result_bayes["map_only"],
            "gt_only": result_bayes["gt_only"]}


def analyze_sequence(sequence, predictions: dict, gt: dict, config: StudyConfig) -> dict:
  """Fuses one sequence with every rule and the oracle and counts what the study needs.

  Args:
    sequence: an `RGBDSequence` (depth, poses, camera) with `labels`.
    predictions: `det`, `mean`, `var`, each `(T, H, W, K)` (see `frontend.FrontEnd`).
    gt: GT voxel labels (`coords (G, 3)`, `labels (G,)`), e.g. `datasets.gt_voxel_labels`.
    config: the study's configuration.

  Returns:
    dict: `confusion` (method → `(K, K)` int64, the rules and `ORACLE`), `correct` (method →
    `(3,)` correctly labelled voxels per headroom category), `headroom` (`(3,)` scored voxels
    per category), `alpha_hist` (`(2, nb)` pixel observations per α bin, right then wrong),
    `pixels` (right and wrong observation counts), `matched`/`map_only`/`gt_only` (Bayesian
    map vs GT). `SequenceAnalysis` computes the same chunk by chunk.
  """
  _check_predictions(sequence, predictions)
  analysis = SequenceAnalysis(gt, config, predictions["mean"].shape[-1])
  analysis.add(sequence, predictions)
  return analysis.result()


# --- statistics over sequences -----------------------------------------------------------------
def histogram_median(counts, edges=ALPHA_EDGES) -> float:
  """Median of a histogram (linear within the bin where the cumulative share crosses ½)."""
  counts = np.asarray(counts, np.float64)
  total = counts.sum()
  if total <= 0:
    return float("nan")
  cum = np.cumsum(counts)
  i = int(np.searchsorted(cum, total / 2.0))
  before = cum[i] - counts[i]
  frac = (total / 2.0 - before) / counts[i] if counts[i] > 0 else 0.0
  return float(edges[i] + frac * (edges[i + 1] - edges[i]))


def _iv(interval: stats.Interval) -> dict:
  return {"estimate": interval.estimate, "low": interval.low, "high": interval.high}


def summarize(per_sequence: list, config: StudyConfig) -> dict:
  """Bootstrap summaries per shift from the per-sequence results.

  Args:
    per_sequence: `analyze_sequence` outputs with `shift` and `unit` keys added, covering
      every `(unit, shift)` of the config.
    config: the study's configuration.

  Returns:
    dict shift (str) → `methods` (method → `miou`, `accuracy` intervals), `differences`
    ("A − B" → `miou`, `accuracy` intervals), `headroom` (category → share interval),
    `recovered` (method → interval of the share of outvoted-right voxels labelled right, and
    `accuracy_by_category`), `oracle_share` (rule → interval of its mIoU gain over Bayes as a
    share of the oracle's, `stats.headroom_share`), `class_iou` (method → per-class IoU of the
    confusions summed over all sequences, NaN for a class absent from GT and map), `ece` (method
    → interval of its map ECE) and `ece_differences` ("A − Bayesian" → paired interval of the
    ECE difference), `alpha` (`median_right`, `median_wrong`, `auroc` interval,
    `right_share` interval of right pixel observations), `num_sequences`.
  """
  methods = config.methods
  out = {}
  for group, seq in _groups(per_sequence, config):
    counts = stats.resample_counts(len(seq), config.num_resamples, seed=config.bootstrap_seed)
    kw = dict(counts=counts, confidence=config.confidence)
    cms = {m: np.stack([r["confusion"][m] for r in seq]) for m in methods}
    res = {"num_sequences": len(seq), "methods": {}, "differences": {}, "headroom": {},
           "recovered": {}, "oracle_share": {}, "class_iou": {}}
    for m in methods:
      res["methods"][display(m)] = {"miou": _iv(stats.bootstrap(cms[m], stats.miou, **kw)),
                                    "accuracy": _iv(stats.bootstrap(cms[m], stats.accuracy,
                                                                    **kw))}
      res["class_iou"][display(m)] = [float(v) for v in metrics.iou_from_confusion(cms[m].sum(0))]
    for a, b in config.comparisons:
      if a in cms and b in cms:
        res["differences"][f"{display(a)} − {display(b)}"] = {
            "miou": _iv(stats.paired_difference(cms[a], cms[b], stats.miou, **kw)),
            "accuracy": _iv(stats.paired_difference(cms[a], cms[b], stats.accuracy, **kw))}
    for m in methods:
      if m not in ("bayes", ORACLE):
        res["oracle_share"][display(m)] = _iv(stats.headroom_share(
            cms[m], cms["bayes"], cms[ORACLE], stats.miou, **kw))
    head = np.stack([r["headroom"] for r in seq])                       # (S, 3)
    total = head.sum(1)
    for c, cname in enumerate(HEADROOM):
      res["headroom"][cname] = _iv(stats.bootstrap(np.stack([head[:, c], total], -1),
                                                   stats.ratio, **kw))
    for m in methods:
      corr = np.stack([r["correct"][m] for r in seq])                   # (S, 3)
      res["recovered"][display(m)] = {
          "share": _iv(stats.bootstrap(np.stack([corr[:, 1], head[:, 1]], -1), stats.ratio,
                                       **kw)),
          "accuracy_by_category": {cname: float(stats.ratio([corr[:, c].sum(),
                                                             head[:, c].sum()]))
                                   for c, cname in enumerate(HEADROOM)}}
    hist = np.stack([r["alpha_hist"] for r in seq])                      # (S, 2, nb)
    pix = np.array([[r["pixels"]["right"], r["pixels"]["right"] + r["pixels"]["wrong"]]
                    for r in seq])
    res["alpha"] = {"median_right": histogram_median(hist[:, 0].sum(0)),
                    "median_wrong": histogram_median(hist[:, 1].sum(0)),
                    "auroc": _iv(stats.bootstrap(hist, metrics.auroc_from_histograms, **kw)),
                    "right_share": _iv(stats.bootstrap(pix, stats.ratio, **kw))}
    if all("calibration" in r for r in seq):
      bins = {m: np.stack([r["calibration"][m] for r in seq])
              for m in methods if m in seq[0]["calibration"]}
      res["ece"] = {display(m): _iv(stats.bootstrap(b, metrics.ece_from_bins, **kw))
                    for m, b in bins.items()}
      if "bayes" in bins:                              # each rule's ECE − Bayes's, paired
        res["ece_differences"] = {
            f"{display(m)} − {display('bayes')}": _iv(stats.paired_difference(
                b, bins["bayes"], metrics.ece_from_bins, **kw))
            for m, b in bins.items() if m != "bayes"}
    if all("feature_hist" in r for r in seq):
      res["feature_auroc"] = {
          name: _iv(stats.bootstrap(np.stack([r["feature_hist"][name] for r in seq]),
                                    metrics.auroc_from_histograms, **kw))
          for name in seq[0]["feature_hist"]}
    out[group] = res
  return out


DATA_GROUP = "data"


def _groups(per_sequence: list, config: StudyConfig) -> list:
  """`[(group, results)]`: one group per shift of the embedded grid, each with its units in
  the grid's order; with `config.data`, one group of all sequences in the order given."""
  if config.data:
    return [(DATA_GROUP, list(per_sequence))]
  units = config.run.units
  out = []
  for shift in config.run.shifts:
    rows = {r["unit"]: r for r in per_sequence if r["shift"] == float(shift)}
    missing = [u for u in units if tuple(u) not in rows]
    if missing:
      raise ValueError(f"no result for shift {shift} and units {missing}")
    out.append((f"{float(shift):g}", [rows[tuple(u)] for u in units]))
  return out


def display(method: str) -> str:
  """Table name of a rule name, `LEARNED`, `GLFS`, a variant or `ORACLE`."""
  if method.startswith(VARIANT_PREFIX):
    return f"Learned ({method[len(VARIANT_PREFIX):]})"
  return ({ORACLE: "Oracle", LEARNED: "Learned", GLFS: "GLFS"}.get(method)
          or jf.rules.PAPER_RULES[method][0])


# --- tables and figures ------------------------------------------------------------------------
def _cell(iv: dict, scale: float = 100.0, signed: bool = False) -> str:
  if iv["estimate"] is None or not np.isfinite(iv["estimate"]):
    return "–"
  fmt = "{:+.1f}" if signed else "{:.1f}"
  return (fmt.format(scale * iv["estimate"]) +
          f" [{scale * iv['low']:.1f}, {scale * iv['high']:.1f}]")


def _group_title(group: str) -> str:
  """A table column's title: "shift 0.5" for an embedded shift, the group's name otherwise."""
  return f"shift {group}" if group != DATA_GROUP else "your data"


def format_tables(summary: dict, config: StudyConfig, note: str = "") -> str:
  """The study's Markdown: mIoU, accuracy, paired differences, headroom, front-end α."""
  shifts = list(summary)
  first = summary[shifts[0]]
  conf = f"{100 * config.confidence:g} %"
  head = "| Method | " + " | ".join(_group_title(s) for s in shifts) + " |"
  rule = "|---|" + "---|" * len(shifts)
  parts = [f"# Fusion study\n\n{note}\n\n"
           "How to read: intervals are percentile bootstrap intervals over sequences (resampled "
           "with replacement; confusion matrices summed over the resample, then mIoU / accuracy), "
           "differences are paired (both methods on the same resamples). A pixel observation "
           "votes for the argmax of the MC mean and is right when that is its voxel's GT label. "
           "A scored GT voxel is *mostly right* when the right class has the most votes, "
           "*outvoted right* when some votes are right but another class has as many or more, "
           "*never right* when no vote is right; a rule *recovers* an outvoted-right voxel when "
           "its map labels it correctly. The *oracle* fuses only the right observations with "
           "the Bayesian rule (never-right voxels keep the Bayesian label): the bound for rules "
           "that weight observations. α = −log var of the predicted class (the D rules' "
           "weight)."]
  for metric, title in (("miou", "mIoU"), ("accuracy", "Accuracy")):
    lines = [f"## {title} (%) with {conf} bootstrap intervals over sequences", "", head, rule]
    for m in first["methods"]:
      lines.append(f"| {m} | " + " | ".join(_cell(summary[s]["methods"][m][metric])
                                              for s in shifts) + " |")
    parts.append("\n".join(lines))
  for metric, title in (("miou", "mIoU"), ("accuracy", "accuracy")):
    lines = [f"## Paired differences of {title} (points, {conf} paired-bootstrap intervals)",
             "", head.replace("Method", "Difference"), rule]
    for d in first["differences"]:
      lines.append(f"| {d} | " + " | ".join(_cell(summary[s]["differences"][d][metric],
                                                    signed=True) for s in shifts) + " |")
    parts.append("\n".join(lines))
  methods = list(first["recovered"])
  lines = ["## Voxel headroom (% of scored GT voxels) and % of outvoted-right voxels recovered",
           "", "| Shift | " + " | ".join(HEADROOM) + " | " +
           " | ".join(f"{m} recovers" for m in methods) + " |",
           "|---|" + "---|" * (len(HEADROOM) + len(methods))]
  for s in shifts:
    r = summary[s]
    lines.append(f"| {s} | " + " | ".join(_cell(r["headroom"][c]) for c in HEADROOM) + " | " +
                 " | ".join(_cell(r["recovered"][m]["share"]) for m in methods) + " |")
  parts.append("\n".join(lines))
  lines = [f"## Share of the oracle's mIoU headroom recovered (%, {conf} paired-bootstrap "
           "intervals): (mIoU − Bayes) / (oracle − Bayes)", "",
           head.replace("Method", "Rule"), rule]
  for m in first["oracle_share"]:
    lines.append(f"| {m} | " + " | ".join(_cell(summary[s]["oracle_share"][m], signed=True)
                                          for s in shifts) + " |")
  parts.append("\n".join(lines))
  for s in dict.fromkeys([shifts[0], shifts[-1]]):
    ious = summary[s]["class_iou"]
    num_classes = len(next(iter(ious.values())))
    names = (config.class_names if len(config.class_names) == num_classes
             else [str(i) for i in range(num_classes)])
    lines = [f"## Per-class IoU (%) at {_group_title(s)}, confusions summed over its sequences",
             "",
             "| Method | " + " | ".join(names) + " |", "|---|" + "---|" * num_classes]
    for m, iou in ious.items():
      lines.append(f"| {m} | " + " | ".join("–" if not np.isfinite(v) else f"{100 * v:.1f}"
                                           for v in iou) + " |")
    parts.append("\n".join(lines))
  lines = ["## Front end: right pixel observations and α = −log var of the predicted class", "",
           "| Shift | right pixels (%) | median α right | median α wrong | AUROC(α: right vs "
           "wrong) |", "|---|---|---|---|---|"]
  for s in shifts:
    a = summary[s]["alpha"]
    auroc = a["auroc"]
    auroc_cell = ("–" if not np.isfinite(auroc["estimate"]) else
                  f"{auroc['estimate']:.3f} [{auroc['low']:.3f}, {auroc['high']:.3f}]")
    lines.append(f"| {s} | {_cell(a['right_share'])} | {a['median_right']:.2f} | "
                 f"{a['median_wrong']:.2f} | {auroc_cell} |")
  parts.append("\n".join(lines))
  if "ece" in first:
    lines = [f"## Map calibration: ECE of the voxel posteriors (%, {metrics.CALIBRATION_BINS} "
             f"bins of the top probability, {conf} bootstrap intervals; lower is better)", "",
             head, rule]
    for m in first["ece"]:
      lines.append(f"| {m} | " + " | ".join(_cell(summary[s]["ece"][m]) for s in shifts) + " |")
    parts.append("\n".join(lines))
  if "ece_differences" in first:
    lines = [f"## Paired differences of map ECE (points, {conf} paired-bootstrap intervals; "
             "below 0: better calibrated than Bayes)", "", head.replace("Method", "Difference"),
             rule]
    for d in first["ece_differences"]:
      lines.append(f"| {d} | " + " | ".join(_cell(summary[s]["ece_differences"][d], signed=True)
                                            for s in shifts) + " |")
    parts.append("\n".join(lines))
  if "feature_auroc" in first:
    names = list(first["feature_auroc"])
    lines = [f"## Per-pixel features: AUROC of right vs wrong observations ({conf} bootstrap "
             "intervals; below 0.5: lower on right observations)", "",
             "| Feature | " + " | ".join(_group_title(s) for s in shifts) + " |", rule]
    for name in names:
      cells = []
      for s in shifts:
        iv = summary[s]["feature_auroc"][name]
        cells.append("–" if iv["estimate"] is None or not np.isfinite(iv["estimate"]) else
                     f"{iv['estimate']:.3f} [{iv['low']:.3f}, {iv['high']:.3f}]")
      lines.append(f"| {name} | " + " | ".join(cells) + " |")
    parts.append("\n".join(lines))
  return "\n\n".join(parts) + "\n"


def _csv(summary: dict) -> str:
  buf = _io.StringIO()
  w = csv.writer(buf)
  w.writerow(["shift", "section", "name", "metric", "estimate", "low", "high"])

  def row(s, section, name, metric, iv):
    w.writerow([s, section, name, metric] + [f"{iv[k]:.6f}" for k in ("estimate", "low",
                                                                        "high")])

  for s, r in summary.items():
    for m, v in r["methods"].items():
      for metric in ("miou", "accuracy"):
        row(s, "method", m, metric, v[metric])
    for d, v in r["differences"].items():
      for metric in ("miou", "accuracy"):
        row(s, "difference", d, metric, v[metric])
    for c, v in r["headroom"].items():
      row(s, "headroom", c, "share", v)
    for m, v in r["recovered"].items():
      row(s, "recovered", m, "share_of_outvoted_right", v["share"])
    for m, v in r.get("oracle_share", {}).items():
      row(s, "oracle_share", m, "miou_gain_share", v)
    row(s, "front_end", "alpha", "auroc", r["alpha"]["auroc"])
    for m, v in r.get("ece", {}).items():
      row(s, "ece", m, "ece", v)
    for d, v in r.get("ece_differences", {}).items():
      row(s, "ece_difference", d, "ece", v)
    for name, v in r.get("feature_auroc", {}).items():
      row(s, "feature_auroc", name, "auroc", v)
    row(s, "front_end", "pixels", "right_share", r["alpha"]["right_share"])
  return buf.getvalue()


def write_outputs(out_dir: str, summary: dict, per_sequence: list, config: StudyConfig, *,
                  model_id: str, timing: dict) -> list:
  """Writes the tables (Markdown, CSV, JSON) and the four PNG figures; returns the paths."""
  os.makedirs(out_dir, exist_ok=True)
  run = config.run
  if config.data:
    shifts = np.array([0.0])
    note = (f"{len(per_sequence)} sequences of your data ({', '.join(config.data)}; "
            f"{per_sequence[0].get('source', '')}), β = {run.beta}, {run.voxel_size} m voxels, "
            f"pixel aggregation: {run.aggregate}; classes {', '.join(config.class_names)}; ")
  else:
    shifts = np.array([float(s) for s in config.run.shifts])
    note = (f"{len(run.units)} sequences per shift ({len(run.layout_seeds)} layout seed(s) × "
            f"{len(run.envs)} environment(s) × {len(run.trajectories)} trajectory(ies)), "
            f"{run.num_frames} frames at {run.height}×{run.width}, M = {run.num_samples}, "
            f"β = {run.beta}, {run.voxel_size} m voxels, pixel aggregation: {run.aggregate}; "
            f"layout seeds {list(run.layout_seeds)}; ")
  note += (
          f"{config.num_resamples} bootstrap resamples; front end `{model_id}`; "
          + (f"learned rule `{config.learned_source or 'given parameters'}`; "
             if config.learned is not None else "")
          + (f"GLFS `{config.glfs_source or 'given parameters'}`; "
             if config.glfs is not None else "")
          + "".join(f"variant {v[0]}; " for v in config.variants)).rstrip("; ") + "."
  if config.data:
    note += "".join(f" {r['sequence']}: {r['frames']} frames" + (
        f" ({r['skipped']} without a prediction, skipped)" if r.get("skipped") else "") + ";"
        for r in per_sequence)
  table = format_tables(summary, config, note)
  paths = {n: os.path.join(out_dir, n) for n in (
      "study.md", "study.csv", "study.json", "timing.json", "miou_vs_shift.png",
      "differences_vs_shift.png", "headroom.png", "alpha_hist.png")}
  reports.write_text(paths["study.md"], table)
  reports.write_text(paths["study.csv"], _csv(summary))
  # What the study found (study.json, the tables, the figures) does not depend on how it was
  # run: the same bytes from one process or several. How long it took goes to timing.json.
  reports.write_json(paths["study.json"], {
      "config": dataclasses.asdict(config), "model": model_id,
      "headroom_categories": list(HEADROOM), "alpha_edges": ALPHA_EDGES,
      "summary": summary,
      "sequences": [{k: v for k, v in r.items() if k != "seconds"} for r in per_sequence]},
      indent=None)
  reports.write_json(paths["timing.json"], {
      **timing, "sequences": {r["sequence"]: r.get("seconds") for r in per_sequence}}, indent=1)

  def curves(section, metric):
    names = summary[next(iter(summary))][section]
    return {n: tuple(np.array([summary[s][section][n][metric][k] for s in summary], float)
                     for k in ("estimate", "low", "high")) for n in names}

  if config.data:      # one group: no curves over shifts
    for name in ("miou_vs_shift.png", "differences_vs_shift.png"):
      del paths[name]
  else:
    _shift_figures(paths, summary, shifts)
  shares = np.array([[summary[s]["headroom"][c]["estimate"] for c in HEADROOM]
                     for s in summary], float)
  recovered = {m: np.array([summary[s]["recovered"][m]["share"]["estimate"] for s in summary],
                           float) for m in summary[next(iter(summary))]["recovered"]}
  figures.headroom_bars(paths["headroom.png"], shifts, np.nan_to_num(shares), HEADROOM,
                        recovered)
  groups = _groups(per_sequence, config)
  hist = np.stack([np.sum([r["alpha_hist"] for r in rows], axis=0)
                   for _, rows in groups])                                    # (groups, 2, nb)
  figures.alpha_histograms(paths["alpha_hist.png"], shifts, ALPHA_EDGES, hist[:, 0], hist[:, 1])
  return list(paths.values())


def _shift_figures(paths: dict, summary: dict, shifts: np.ndarray) -> None:
  """mIoU and paired differences against the shift, with their intervals."""
  def curves(section, metric):
    names = summary[next(iter(summary))][section]
    return {n: tuple(np.array([summary[s][section][n][metric][k] for s in summary], float)
                     for k in ("estimate", "low", "high")) for n in names}

  figures.bands_vs_shift(paths["miou_vs_shift.png"],
                         shifts, {"mIoU": curves("methods", "miou"),
                                  "accuracy": curves("methods", "accuracy")}, ylabel="%")
  rule_diffs = {m: {n: c for n, c in curves("differences", m).items()
                    if not n.startswith(display(ORACLE))} for m in ("miou", "accuracy")}
  figures.bands_vs_shift(paths["differences_vs_shift.png"], shifts,
                         {"mIoU difference": rule_diffs["miou"],
                          "accuracy difference": rule_diffs["accuracy"]},
                         ylabel="points", zero_line=True)


# --- the whole study ---------------------------------------------------------------------------
def run_study(config: StudyConfig, out_dir: str, *, cache_dir: Optional[str] = None,
              checkpoint: Optional[str] = None, front_end=None) -> dict:
  """Runs the grid, writes tables and figures, returns the summary.

  Args:
    config: what to run (validated here).
    out_dir: output folder.
    cache_dir: front-end cache folder (default `OUT/cache`; the demo's cache can be shared).
    checkpoint: network weights (default: the shipped ones); ignored when `front_end` is given.
    front_end: an object with `model_id` (str) and `predict(rgb (T, H, W, 3) uint8, *,
      num_samples, key) -> (det, mean, var)` each `(T, H, W, K)`, instead of the shipped
      network (e.g. a simulated one).

  Returns:
    dict with `summary` (see `summarize`), `table` (Markdown), `files`, `timing` (seconds per
    stage and in all) and `sequences` (per-sequence raw results).
  """
  from jaxfusion import datasets
  config.validate()
  start, start_cpu = time.perf_counter(), time.process_time()
  os.makedirs(out_dir, exist_ok=True)
  cache_dir = cache_dir or os.path.join(out_dir, "cache")
  front_end = front_end if front_end is not None else frontend.FrontEnd(checkpoint)
  timing = {name: 0.0 for name in ("render_s", "front_end_s", "fusion_s", "render_cpu_s",
                                    "front_end_cpu_s", "fusion_cpu_s")}
  local = {}
  run = config.run
  grid = run.grid
  mine = distributed.my_items(len(grid))   # all of them in one process
  for index in tqdm(mine, desc="study" if distributed.process_count() == 1 else
                    f"study, process {distributed.process_index()}"):
    (seed, env, traj), shift = grid[index]
    t0, c0 = time.perf_counter(), time.process_time()
    seq = datasets.load_spec(datasets.SequenceSpec("synthetic", env, traj, run.domain),
                             num_frames=run.num_frames, height=run.height, width=run.width,
                             layout_seed=seed, shift=shift)
    gt = datasets.gt_voxel_labels(seq, voxel_size=run.voxel_size, capacity=run.capacity)
    t1, c1 = time.perf_counter(), time.process_time()
    preds = frontend.cached_predictions(front_end, seq, layout_seed=seed, shift=shift,
                                        num_samples=run.num_samples, mc_seed=run.mc_seed,
                                        cache_dir=cache_dir)
    t2, c2 = time.perf_counter(), time.process_time()
    result = analyze_sequence(seq, preds, gt, config)
    t3, c3 = time.perf_counter(), time.process_time()
    for name, wall, cpu in (("render", t1 - t0, c1 - c0), ("front_end", t2 - t1, c2 - c1),
                            ("fusion", t3 - t2, c3 - c2)):
      timing[f"{name}_s"] += wall
      timing[f"{name}_cpu_s"] += cpu
    result.update(unit=(int(seed), env, int(traj)), shift=float(shift),
                  sequence=f"{seq.name}_s{seed}_shift{float(shift):g}",
                  seconds={"wall": t3 - t0, "cpu": c3 - c0})
    local[index] = result
  per_sequence = distributed.gather_items(local, len(grid))
  summary = summarize(per_sequence, config)
  timing = _all_processes(timing, start, start_cpu)
  files = write_outputs(out_dir, summary, per_sequence, config, model_id=front_end.model_id,
                        timing=timing) if distributed.is_main() else []
  timing["total_s"] = time.perf_counter() - start
  distributed.barrier("study outputs written")
  return {"summary": summary, "table": format_tables(summary, config), "files": files,
          "timing": timing, "sequences": per_sequence}


def _all_processes(timing: dict, start: float, start_cpu: float) -> dict:
  """This process's stage times with the total so far, and (with several processes) every
  process's under `processes` and the CPU time summed over them."""
  timing = dict(timing, total_s=time.perf_counter() - start,
                total_cpu_s=time.process_time() - start_cpu)
  if distributed.process_count() == 1:
    return timing
  everyone = distributed.allgather_objects(timing)
  return dict(timing, total_cpu_s=sum(t["total_cpu_s"] for t in everyone), processes=everyone)


def fitted_for(config: StudyConfig, num_classes: int) -> StudyConfig:
  """The config without the fitted rows (learned, GLFS, variants) whose parameters are for
  another number of classes than the data's, each left out with one printed line."""
  changes, variants = {}, []
  for key, family, params in ((LEARNED, "learned", config.learned),
                              (GLFS, "glfs", config.glfs)):
    if params is not None:
      k = flags.fitted_for_other(family, params, num_classes)
      if k is not None:
        print(f"note: {display(key)} is left out: its parameters are fitted for {k} classes, "
              f"the data has {num_classes} (fit them with `jaxfusion learn-rule --data ...` "
              f"and pass --{'learned-rule' if key == LEARNED else 'glfs'} PARAMS_JSON)")
        changes[key] = None
  for variant in config.variants:
    k = flags.fitted_for_other(flags.variant_family(variant), variant[1], num_classes)
    if k is not None:
      print(f"note: variant {variant[0]} is left out: fitted for {k} classes, the data has "
            f"{num_classes}")
    else:
      variants.append(variant)
  return dataclasses.replace(config, variants=tuple(variants), **changes)


def run_study_data(config: StudyConfig, out_dir: str, specs, options, *,
                   front_end=None, checkpoint: Optional[str] = None) -> dict:
  """The study on a researcher's sequences (`--data`): one group of sequences, each with its
  own predictions and GT, streamed from disk a chunk at a time (`lab.sequences.Streamed`,
  `SequenceAnalysis`), every rule and the oracle, paired intervals.

  Args:
    config: rules, β, aggregation, fitted rows and statistics (its grid is not used).
    out_dir: output folder.
    specs: the sequences (`SequenceSpec`s, e.g. `datasets.sets.expand` of `--data`).
    options: `lab.sequences.DataOptions` (sizes, stride, predictions, label space, class map).
    front_end: a front end for sequences without precomputed predictions (default: the shipped
      network, loaded only when needed).
    checkpoint: its weights.

  Returns:
    As `run_study`.
  """
  from jaxfusion.lab import sequences   # pylint: disable=import-outside-toplevel
  specs = list(specs)
  if not specs:
    raise ValueError("--data names no sequence")
  start, start_cpu = time.perf_counter(), time.process_time()
  os.makedirs(out_dir, exist_ok=True)
  options = dataclasses.replace(options, voxel_size=config.run.voxel_size,
                                cache_dir=options.cache_dir or os.path.join(out_dir, "cache"))
  if options.predictions is None and front_end is None:
    front_end = frontend.FrontEnd(checkpoint, class_names=None)
  model_id = front_end.model_id if options.predictions is None else "precomputed"
  local, classes = {}, None
  # Every process reads the first sequence's label space (a header, not its frames), so that
  # all of them fit the same configuration, then fuses only its own share of the sequences.
  # (An embedded first sequence is rendered for it; process 0, which fuses it, reuses it.)
  first = sequences.Streamed(specs[0], options, front_end=front_end)
  classes = first.class_names
  config = fitted_for(dataclasses.replace(
      config, data=tuple(str(s) for s in specs), class_names=classes), len(classes))
  config.validate()
  for index in tqdm(distributed.my_items(len(specs)), desc="study"):
    spec = specs[index]
    t0, c0 = time.perf_counter(), time.process_time()
    item = first if index == 0 else sequences.Streamed(spec, options, front_end=front_end)
    if item.class_names != classes:
      raise ValueError(f"{item.name}: its classes {list(item.class_names)} are not the first "
                       f"sequence's {list(classes)}; one study, one label space")
    analysis = SequenceAnalysis(item.gt(), config, len(classes), grow=True)
    for frames, preds in item.chunks():
      if preds["var"] is None:
        raise ValueError(f"{item.name}: the predictions hold no 'var' (or 'samples'); the "
                         "robust rules and the study's α need the MC variance")
      analysis.add(frames, preds)
    if item.skipped:
      tqdm.write(f"{item.name}: {item.skipped} frames have no prediction; skipped")
    result = analysis.result()
    result.update(unit=item.name, shift=DATA_GROUP, sequence=item.name, source=item.source,
                  frames=item.frames, skipped=item.skipped,
                  seconds={"wall": time.perf_counter() - t0, "cpu": time.process_time() - c0})
    local[index] = result
  per_sequence = distributed.gather_items(local, len(specs))
  summary = summarize(per_sequence, config)
  timing = _all_processes({}, start, start_cpu)
  files = write_outputs(out_dir, summary, per_sequence, config, model_id=model_id,
                        timing=timing) if distributed.is_main() else []
  distributed.barrier("study outputs written")
  return {"summary": summary, "table": format_tables(summary, config), "files": files,
          "timing": timing, "sequences": per_sequence, "config": config}


# --- command line ------------------------------------------------------------------------------
def add_parser(subparsers) -> argparse.ArgumentParser:
  """Adds `jaxfusion study`."""
  p = subparsers.add_parser(
      "study", help="the fusion experiment as a study: rules × shifts × seeds × sequences, "
                    "with bootstrap intervals, headroom and oracle")
  p.add_argument("--quick", action="store_true",
                 help="1 seed × 2 envs × 1 trajectory × 3 shifts, 12 frames at 60×80, M = 8 "
                      "(≤ 3 min on 2 cores)")
  p.add_argument("--out", default="outputs/study", help="output folder")
  flags.add_study_run(p, seed_aliases=("--seeds",),
                      seeds_help=f" (default 1 2 3; the demo uses {DEMO_SEED})")
  flags.add_glfs_rule(p)
  flags.add_data(p)
  flags.add_processes(p)
  p.add_argument("--variant", action="append", default=[], metavar="TAG=PARAMS_JSON",
                 help="another learned rule (a learn-rule params.json) as a row "
                      "'Learned (TAG)', compared with Bayes and the learned row; repeatable")
  p.set_defaults(func=main)
  return p


def main(args: argparse.Namespace) -> int:
  """Runs `jaxfusion study` from parsed arguments and prints the tables."""
  learned, source = flags.learned_rule(args)
  glfs, glfs_source = flags.glfs_rule(args)
  config = StudyConfig.of(
      args.quick, num_resamples=args.resamples, layout_seeds=flags.as_tuple(args.layout_seeds),
      shifts=flags.as_tuple(args.shifts), envs=flags.as_tuple(args.envs),
      trajectories=flags.as_tuple(args.trajectories), num_frames=args.frames,
      height=args.height, width=args.width, num_samples=args.num_samples, beta=args.beta,
      aggregate=args.aggregate, mc_seed=args.mc_seed, learned=learned, learned_source=source,
      glfs=glfs, glfs_source=glfs_source, variants=flags.learned_variants(args))
  data = flags.data_sets(args, "data")["--data"]
  if data is not None:
    options = flags.run_data_options(args, config.run)
    out = run_study_data(config, args.out, data, options, checkpoint=args.checkpoint)
    if not distributed.is_main():
      return 0
    print(out["table"])
    print(f"wrote {len(out['files'])} files under {args.out}/ in "
          f"{out['timing']['total_s']:.0f} s")
    return 0
  out = run_study(config.validate(), args.out, cache_dir=args.cache, checkpoint=args.checkpoint)
  if not distributed.is_main():
    return 0
  print(out["table"])
  t = out["timing"]
  print(f"wrote {len(out['files'])} files under {args.out}/ (study.md/.csv/.json, timing.json, "
        f"miou_vs_shift.png, differences_vs_shift.png, headroom.png, alpha_hist.png) in "
        f"{t['total_s']:.0f} s (render + GT {t['render_s']:.0f} s, front end "
        f"{t['front_end_s']:.0f} s, fusion and counts {t['fusion_s']:.0f} s; CPU time "
        f"{t['total_cpu_s']:.0f} s)")
  return 0
