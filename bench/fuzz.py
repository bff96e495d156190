"""`python -m bench.fuzz [--frames N] [--seed S] [--quick]`: a soak of adversarial frames.

Feeds seeded adversarial frames (default 10⁴ in all) through the three public entry points —
`fuse_frame` on single frames, `fuse_sequence` on stacks of 4 and `fuse_batch` on 2 × 2 batches
built with `stack_sequences` — cycling through every rule of `rules.PAPER_RULES`. Frames mix
depth holes (0, negative, NaN, ±inf, 1e30, 1e-30), NaN / +inf / > 1 / one-hot / all-zero
probabilities, zero / NaN / +inf / 1e30 / within-tolerance negative variances, extreme finite
poses (translations of 1e6–1e9 m, past the key limit at the top) and small maps (2^8–2^10
slots) that overfill. About one call in eight carries an input that must be refused with a
ValueError/TypeError: a non-finite or near-singular pose, probabilities with the wrong K,
negative probabilities or variances, or no variance for a rule that needs one. Every other map
carries free-space clearing (`FREE_SPACE_CONFIG`, docs/equations.md §10): the schedule runs each
(entry point, shape, rule) through all its shapes with clearing off, then all with it on; and
about one frame in three looks again from an earlier frame's pose (`revisit`), at a wall behind
what that frame saw (clearing frees it) or at the same surface (a freed voxel restarts).

After every call it checks (docs/equations.md §1.3, §2.1, §5):
  * every row of the map finite; the posterior of every occupied voxel finite, in [0, 1] and
    summing to 1 within 1e-5; its entropy finite and ≥ 0; `num_occupied` ≤ capacity and equal
    to the number of stored keys (a jitted pass over the whole table, with `posterior_fn` and
    `numerics.entropy`, the same math as `read_map`; `read_map` itself, which compiles once per
    number of voxels read out, is called on maps whose read-out is empty or full);
  * the stored keys: the old ones kept, the new ones among the frames' valid voxels (recomputed
    on the host with `camera.depth_to_voxel_keys` and the validity rule of §2.1); the hits
    added equal the valid pixels of stored voxels;
  * with clearing on, instead of the last: after one frame every stored voxel's hits are its
    old ones plus the frame's pixels, or only the frame's pixels where it was free and is hit
    again (a restart); after a stack, at most the old hits plus the stack's pixels, at least
    the last frame's pixels, unchanged where no frame hit it; the voxels the last frame hit are
    read out (occupied), every read-out voxel is stored, and the occupancy log-odds are finite,
    within the clamps on stored slots and 0 on empty ones; the read-out counts the stored
    voxels that are not free (`read_map` and `map_stats(...)["free"]`);
  * drops: for one frame, exactly `num_dropped` grows by the new valid voxels that were not
    stored; for a stack, at least that; a call with more new valid voxels than free slots must
    drop; `map_stats(...)["dropped"]` equals `num_dropped`, with `MapFullWarning` iff > 0;
  * refusals: an input that must be refused raises ValueError/TypeError (anything else, or an
    acceptance, is a violation), and a valid input is never refused.

Memory: the current RSS (`/proc/self/statm`) every 500 frames after a warm-up that compiles
every shape, rule and entry point first. Prints a Markdown summary and writes
`bench/results/fuzz.json`.
"""

import argparse
import collections
import gc
import json
import os
import pathlib
import platform
import subprocess
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

import jaxfusion as jf
from jaxfusion import camera as camera_lib
from jaxfusion import hashing
from jaxfusion import numerics

# Every shape the soak compiles, listed up front (compile time is not the point): per entry
# point, (name, height, width, K, capacity, with var for the baseline rules; D and D+R always
# get one). Maps of `fuse_frame` and `fuse_sequence` persist over calls (and so fill up) and
# pick a voxel size of 0.02 m (fills fast) or 0.1 m, a traced leaf that does not recompile.
FRAME_SHAPES = (("F1", 12, 16, 3, 2**8, True), ("F2", 24, 32, 5, 2**10, True),
                ("F3", 12, 16, 3, 2**8, False))
SEQUENCE_SHAPES = (("S1", 12, 16, 3, 2**8, True), ("S2", 24, 32, 5, 2**10, True))
BATCH_SHAPES = (("B1", 16, 20, 4, 2**9, True),)
SEQUENCE_LENGTH = 4
BATCH_SIZE, BATCH_LENGTH = 2, 2
BATCH_VOXEL_SIZE = 0.05          # static in `fuse_batch`: one value, one compilation per rule
VOXEL_SIZES = (0.02, 0.1)
# Calls in one cycle of the schedule: 12 frames per cycle, a third through each entry point.
SCHEDULE = ("frame", "frame", "frame", "frame", "sequence", "batch")
REJECT_PROBABILITY = 0.12
# A frame looks again from an earlier frame's pose (`revisit`), so that clearing has voxels to
# free and to restart.
REVISIT_PROBABILITY = 0.3
REJECT_REASONS = ("pose_nonfinite", "pose_near_singular", "k_mismatch", "negative_probs",
                  "negative_var", "missing_var")
RSS_EVERY = 500
SUM_TOL = 1e-5
BOUND_TOL = 1e-6                  # float32 rounding of exp(normalised log p) may pass 1 by ulps
MAX_EXAMPLES = 10
# Maps without and with free-space clearing (docs/equations.md §10), in turn. The maps with it
# take a miss probability of 0.2 (OctoMap's 0.4 needs three misses to free a voxel hit once), so
# that voxels are freed and restarted within a map's short life.
FREE_SPACE = (False, True)
FREE_SPACE_CONFIG = jf.FreeSpaceConfig(prob_miss=0.2)
RULE_NAMES = tuple(jf.rules.PAPER_RULES)
NEEDS_VAR = {name: jf.rules.by_name(name).requires_var for name in RULE_NAMES}


def _camera(height: int, width: int) -> jf.Camera:
  return jf.Camera(0.8 * width, 0.8 * width, (width - 1) / 2, (height - 1) / 2)


def _rss_mb() -> float:
  with open("/proc/self/statm") as f:
    return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


_COMPILES = [0]


def _count_compile(event: str, _seconds: float, **_) -> None:
  if event == "/jax/core/compile/backend_compile_duration":
    _COMPILES[0] += 1


jax.monitoring.register_event_duration_secs_listener(_count_compile)


def _uptime() -> str:
  try:
    return subprocess.run(["uptime"], capture_output=True, text=True, check=False).stdout.strip()
  except OSError:
    return "unknown"


# --- the generator ------------------------------------------------------------------------
def _rotation(rng) -> np.ndarray:
  q, r = np.linalg.qr(rng.normal(size=(3, 3)))
  q = q * np.sign(np.diag(r))
  if np.linalg.det(q) < 0:
    q[:, 0] = -q[:, 0]
  return q


def _pixels(rng, shape, low=0.02, high=0.3):
  """A random mask of `shape` covering a fraction U(low, high) of it."""
  return rng.random(shape) < rng.uniform(low, high)


def make_frame(rng, height: int, width: int, num_classes: int, with_var: bool, features):
  """One adversarial but acceptable frame as NumPy arrays (depth, pose, probs, var | None);
  counts the kinds of bad data it holds in `features`."""
  shape = (height, width)

  def maybe(name, p=0.3):
    hit = rng.random() < p
    if hit:
      features[name] += 1
    return hit

  if maybe("depth_flat_wall", 0.4):
    depth = np.full(shape, rng.uniform(0.5, 4.0)) + rng.normal(0, 0.01, shape)
  else:
    depth = rng.uniform(0.3, 6.0, shape)
  for name, value in (("depth_zero", 0.0), ("depth_negative", -1.0), ("depth_nan", np.nan),
                      ("depth_+inf", np.inf), ("depth_-inf", -np.inf), ("depth_1e30", 1e30),
                      ("depth_1e-30", 1e-30)):
    if maybe(name, 0.2):
      depth[_pixels(rng, shape)] = value
  if maybe("depth_all_holes", 0.03):
    depth[:] = rng.choice([0.0, np.nan, -2.0])

  probs = rng.dirichlet(np.full(num_classes, rng.choice([0.1, 1.0, 10.0])), shape)
  if maybe("probs_one_hot"):
    mask = _pixels(rng, shape, 0.1, 0.6)
    probs[mask] = np.eye(num_classes)[rng.integers(0, num_classes, mask.sum())]
  if maybe("probs_all_zero_pixels"):
    probs[_pixels(rng, shape)] = 0.0
  if maybe("probs_above_1"):
    mask = _pixels(rng, shape)
    probs[mask] *= rng.uniform(1.0, 100.0, (mask.sum(), 1))
  if maybe("probs_nan", 0.2):
    probs[_pixels(rng, shape)] = np.nan
  if maybe("probs_+inf", 0.2):
    mask = _pixels(rng, shape)
    probs[mask, rng.integers(0, num_classes, mask.sum())] = np.inf
  if maybe("probs_frame_one_hot", 0.03):
    probs = np.eye(num_classes)[rng.integers(0, num_classes, shape)]
  if maybe("probs_frame_zero", 0.03):
    probs = np.zeros_like(probs)

  var = None
  if with_var:
    var = rng.uniform(0.0, 0.05, shape + (num_classes,))
    for name, value in (("var_zero", 0.0), ("var_1e30", 1e30), ("var_nan", np.nan),
                        ("var_+inf", np.inf), ("var_-1e-7", -1e-7)):
      if maybe(name, 0.2):
        var[_pixels(rng, shape)] = value
    if maybe("var_frame_zero", 0.05):
      var[:] = 0.0
    if maybe("var_frame_1e30", 0.03):
      var[:] = 1e30

  pose = np.eye(4)
  pose[:3, :3] = _rotation(rng)
  if maybe("pose_extreme_translation", 0.12):
    direction = rng.normal(size=3)
    pose[:3, 3] = direction / np.linalg.norm(direction) * 10.0 ** rng.uniform(6, 9)
  else:
    pose[:3, 3] = rng.normal(0, 0.5, 3)
  as32 = lambda x: None if x is None else np.asarray(x, np.float32)
  return [as32(depth), as32(pose), as32(probs), as32(var)]


def revisit(rng, frame, source, features) -> None:
  """Makes `frame` (a list [depth, pose, probs, var]) look again from `source`'s pose (an
  earlier frame): at a wall 0.3–2 m behind the farthest surface `source` saw (which frees what
  it saw) or, where `source` has depth, at the very same surface (which restarts a voxel freed
  since); the frame's own holes and odd depths stay."""
  valid = lambda d: np.isfinite(d) & (d > 0)
  seen = valid(source[0]) & (source[0] < 1e6)
  keep = valid(frame[0]) & (frame[0] < 1e6)
  if rng.random() < 0.5 or not seen.any():
    features["revisit_behind"] += 1
    far = float(source[0][seen].max()) if seen.any() else 6.0
    frame[0] = np.where(keep, np.float32(far + rng.uniform(0.3, 2.0)), frame[0])
  else:
    features["revisit_same_surface"] += 1
    frame[0] = np.where(keep & seen, source[0], frame[0])
  frame[0] = frame[0].astype(np.float32)
  frame[1] = np.array(source[1], np.float32)


def inject(rng, frames, reason: str, num_classes: int):
  """Makes one frame of `frames` (a list of [depth, pose, probs, var]) one that the public
  entry points must refuse for `reason`; `k_mismatch` and `missing_var` apply to all frames
  (a stack has one K and one var-or-not)."""
  target = frames[rng.integers(len(frames))]
  if reason == "pose_nonfinite":
    target[1][rng.integers(3), rng.integers(4)] = rng.choice([np.nan, np.inf, -np.inf])
  elif reason == "pose_near_singular":
    scale = np.ones(3, np.float32)
    scale[rng.integers(3)] = 10.0 ** rng.uniform(-9, -2)
    target[1][:3, :3] = target[1][:3, :3] * scale[None, :]
  elif reason == "k_mismatch":
    wrong = num_classes + int(rng.choice([-1, 1])) if num_classes > 2 else num_classes + 1
    for f in frames:
      h, w = f[0].shape
      f[2] = rng.dirichlet(np.ones(wrong), (h, w)).astype(np.float32)
      f[3] = None if f[3] is None else np.full((h, w, wrong), 0.01, np.float32)
  elif reason == "negative_probs":
    mask = _pixels(rng, target[0].shape, 0.001, 0.02)
    mask.flat[rng.integers(mask.size)] = True
    target[2][mask, rng.integers(0, num_classes)] = rng.choice([-1e-3, -0.5, -np.inf])
  elif reason == "negative_var":
    mask = _pixels(rng, target[0].shape, 0.001, 0.02)
    mask.flat[rng.integers(mask.size)] = True
    target[3][mask, rng.integers(0, num_classes)] = rng.choice([-1e-3, -1.0, -np.inf])
  elif reason == "missing_var":
    for f in frames:
      f[3] = None
  else:
    raise AssertionError(reason)


# --- host-side expectations ------------------------------------------------------------------
_keys_jit = jax.jit(camera_lib.depth_to_voxel_keys)


def valid_keys(frame, camera, voxel_size):
  """`(keys (n, 3) int32, n_valid_pixels)`: the key of every valid pixel (§2.1), as the engine
  computes it (`depth_to_voxel_keys`, float32)."""
  depth, pose, probs, var = frame
  keys, in_range = _keys_jit(depth, pose, camera, np.float32(voxel_size))
  keys, in_range = np.asarray(keys), np.asarray(in_range)
  k = probs.shape[-1]
  valid = in_range & (depth.reshape(-1) > 0) & np.all(np.isfinite(probs.reshape(-1, k)), -1)
  if var is not None:
    valid &= np.all(np.isfinite(var.reshape(-1, k)), -1)
  return keys[valid]


def key_set(keys: np.ndarray) -> set:
  return {row.tobytes() for row in np.ascontiguousarray(keys, np.int32)}


def snapshot(state) -> dict:
  """What the checks need of a map before a call (copied: the call donates it); with clearing
  on also each stored voxel's hits (`slot_hits`, by key) and the keys that are free."""
  keys = np.asarray(state.keys)
  stored = keys[:, 0] != hashing.EMPTY
  hits = np.asarray(state.hits, np.int64)
  out = {"keys": key_set(keys[stored]), "hits": int(hits.sum()),
         "occupied": int(state.num_occupied), "dropped": int(state.num_dropped)}
  if state.free_space is not None:
    rows = [row.tobytes() for row in np.ascontiguousarray(keys[stored], np.int32)]
    free = np.asarray(state.free_space.log_odds)[stored] <= state.free_space.config.log_occupied
    out["slot_hits"] = dict(zip(rows, hits[stored].tolist()))
    out["free"] = {row for row, f in zip(rows, free) if f}
  return out


def empty_snapshot() -> dict:
  return {"keys": set(), "hits": 0, "occupied": 0, "dropped": 0, "slot_hits": {}, "free": set()}


def pixel_counts(keys: np.ndarray) -> collections.Counter:
  """Valid pixels per voxel key of one frame (`valid_keys`)."""
  return collections.Counter(map(bytes, np.ascontiguousarray(keys, np.int32)))


@jax.jit
def _table_check(state):
  """Reductions over the whole table: finiteness of the rows, posterior and entropy checks on
  the occupied slots (the same `posterior_fn` and `numerics.entropy` as `read_map`)."""
  rows_finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(r)) for r in jax.tree.leaves(state.rows)]))
  posterior, occupied = jf.voxel_posteriors(state)
  entropy = numerics.entropy(posterior)
  occ = occupied[:, None]
  stored = state.keys[:, 0] != hashing.EMPTY
  extra = {}
  if state.free_space is not None:
    log_odds, config = state.free_space.log_odds, state.free_space.config
    within = ((log_odds >= config.log_min - BOUND_TOL) & (log_odds <= config.log_max + BOUND_TOL)
              & jnp.isfinite(log_odds))
    extra["log_odds_ok"] = jnp.all(jnp.where(stored, within, log_odds == 0.0))
  return extra | {
      "rows_finite": rows_finite,
      "posterior_finite": jnp.all(jnp.where(occ, jnp.isfinite(posterior), True)),
      "posterior_min": jnp.min(jnp.where(occ, posterior, 1.0)),
      "posterior_max": jnp.max(jnp.where(occ, posterior, 0.0)),
      "sum_error": jnp.max(jnp.where(occupied, jnp.abs(jnp.sum(posterior, -1) - 1.0), 0.0)),
      "entropy_finite": jnp.all(jnp.where(occupied, jnp.isfinite(entropy), True)),
      "entropy_min": jnp.min(jnp.where(occupied, entropy, 0.0)),
      "stored_keys": jnp.sum(stored, dtype=jnp.int32),
      "observed": jnp.sum(occupied, dtype=jnp.int32),
      "observed_not_stored": jnp.any(occupied & ~stored),
  }


class Soak:
  """Runs calls, checks every map they return, and keeps the counts."""

  def __init__(self, seed: int):
    self.seed = seed
    self.calls = 0
    self.frames = 0
    self.counts = collections.Counter()
    self.rejected_frames = collections.Counter()
    self.rejected_calls = collections.Counter()
    self.features = collections.Counter()
    self.violations = collections.Counter()
    self.violations_by_call = collections.Counter()   # (kind, entry, extreme pose in the call)
    self.examples = []
    self.overfill = collections.Counter()
    self.extremes = {"posterior_max": 0.0, "posterior_min": 1.0, "sum_error": 0.0,
                     "entropy_min": np.inf}
    self.maps = {}

  # --- bookkeeping ---
  def violation(self, kind: str, where: dict, detail: str) -> None:
    self.violations[kind] += 1
    self.violations_by_call[kind, where.get("entry"), where.get("extreme_pose")] += 1
    if len(self.examples) < MAX_EXAMPLES:
      self.examples.append({"kind": kind, **where, "detail": detail[:400]})

  # --- the checks ---
  def check_map(self, state, before: dict, frame_keys: list, single: bool, where: dict,
                read: bool) -> None:
    """All checks of one unbatched map after a call that fused the frames of `frame_keys`."""
    self.counts["maps_checked"] += 1
    capacity = state.capacity
    r = jax.device_get(_table_check(state))
    for name in ("rows_finite", "posterior_finite", "entropy_finite"):
      if not r[name]:
        self.violation(name.replace("_finite", "_not_finite"), where, str(r))
    if r["posterior_min"] < 0.0 or r["posterior_max"] > 1.0 + BOUND_TOL:
      self.violation("posterior_outside_0_1", where, str(r))
    if r["sum_error"] > SUM_TOL:
      self.violation("posterior_not_normalised", where, str(r))
    if r["entropy_min"] < -BOUND_TOL:
      self.violation("entropy_negative", where, str(r))
    for name in ("posterior_max", "sum_error"):
      self.extremes[name] = max(self.extremes[name], float(r[name]))
    for name in ("posterior_min", "entropy_min"):
      self.extremes[name] = min(self.extremes[name], float(r[name]))

    # `read_map` compiles once per number of voxels it reads out: it reads maps whose read-out
    # is empty or full (with clearing on, a full map with free voxels is not read).
    read = read and int(r["observed"]) in (0, capacity)
    after = snapshot(state)
    if after["occupied"] > capacity or after["occupied"] != int(r["stored_keys"]):
      self.violation("occupied_count", where, f"num_occupied {after['occupied']}, stored keys "
                     f"{int(r['stored_keys'])}, capacity {capacity}")
    union = set().union(*map(key_set, frame_keys)) if frame_keys else set()
    if not before["keys"] <= after["keys"]:
      self.violation("keys_lost", where, f"{len(before['keys'] - after['keys'])} keys vanished")
    stray = after["keys"] - before["keys"] - union
    if stray:
      self.violation("stray_keys", where, f"{len(stray)} stored keys of no valid pixel, e.g. "
                     f"{np.frombuffer(next(iter(stray)), np.int32).tolist()}")
    if state.free_space is None:
      stored_pixels = sum(sum(k in after["keys"] for k in map(bytes, np.ascontiguousarray(f)))
                          for f in frame_keys)
      if after["hits"] - before["hits"] != stored_pixels:
        self.violation("hits", where, f"hits grew by {after['hits'] - before['hits']}, valid "
                       f"pixels of stored voxels {stored_pixels}")
      if int(r["observed"]) != int(r["stored_keys"]):
        self.violation("observed_count", where, f"{int(r['observed'])} voxels read out of "
                       f"{int(r['stored_keys'])} stored, without free space")
    else:
      self.check_cleared(r, before, after, frame_keys, single, where)

    new_valid = len(union - before["keys"])
    new_stored = after["occupied"] - before["occupied"]
    dropped = after["dropped"] - before["dropped"]
    free = capacity - before["occupied"]
    missed = new_valid - new_stored
    if single and dropped != missed:
      self.violation("drops_miscounted", where, f"{new_valid} new valid voxels, {new_stored} "
                     f"stored, num_dropped grew by {dropped}")
    if not single and dropped < missed:
      self.violation("drops_undercounted", where, f"{new_valid} new valid voxels, {new_stored} "
                     f"stored, num_dropped grew by only {dropped}")
    if new_valid > free:
      self.overfill["overfilled_maps"] += 1
      self.overfill["dropped_in_overfilled"] += dropped
      if dropped <= 0:
        self.violation("overfill_not_dropped", where, f"{new_valid} new valid voxels, {free} "
                       "free slots, nothing dropped")
    elif dropped > 0:
      self.overfill["dropped_before_full"] += dropped
      self.overfill["maps_dropping_before_full"] += 1
    if after["dropped"] > 0:
      self.overfill["maps_with_drops"] += 1

    with warnings.catch_warnings(record=True) as caught:
      warnings.simplefilter("always")
      stats = jf.map_stats(state)
      if read:
        out = jf.read_map(state)
    warned = sum(issubclass(w.category, jf.MapFullWarning) for w in caught)
    if stats["dropped"] != after["dropped"] or stats["occupied"] != after["occupied"] or (
        state.free_space is not None and stats["free"] != len(after["free"])):
      self.violation("map_stats", where, f"{stats} vs {after['dropped']} dropped")
    if (warned > 0) != (after["dropped"] > 0):
      self.violation("map_full_warning", where, f"{warned} warnings, {after['dropped']} dropped")
    if read:
      self.counts["read_map_calls"] += 1
      p, e = out["posterior"], out["entropy"]
      if len(p) != int(r["observed"]):
        self.violation("read_map_count", where, f"{len(p)} voxels read, {int(r['observed'])} "
                       "observed")
      if len(p) and not (np.all(np.isfinite(p)) and p.min() >= 0.0
                         and p.max() <= 1.0 + BOUND_TOL
                         and np.abs(p.sum(-1) - 1.0).max() <= SUM_TOL
                         and np.all(np.isfinite(e)) and e.min() >= -BOUND_TOL):
        self.violation("read_map_posterior", where, f"min {p.min()}, max {p.max()}")

  def check_cleared(self, r: dict, before: dict, after: dict, frame_keys: list, single: bool,
                    where: dict) -> None:
    """The checks of a map with free-space clearing on that replace the hit count's (module
    docstring): hits per stored voxel with restarts, the last frame's voxels read out, the
    log-odds in their clamps, the read-out within the stored voxels."""
    self.counts["maps_checked_free_space"] += 1
    if not r["log_odds_ok"]:
      self.violation("log_odds", where, str(r))
    if r["observed_not_stored"]:
      self.violation("read_out_not_stored", where, str(r))
    pixels = [pixel_counts(f) for f in frame_keys]
    total = sum(pixels, collections.Counter())
    last = pixels[-1] if pixels else collections.Counter()
    old, new = before["slot_hits"], after["slot_hits"]
    restarted, wrong = 0, []
    for key, hits in new.items():
      n, base = total.get(key, 0), old.get(key, 0)
      if single:
        again = n > 0 and key in before["free"]
        restarted += again
        ok = hits == (0 if again else base) + n
      else:
        ok = hits == base if n == 0 else last.get(key, 0) <= hits <= base + n
      if not ok:
        wrong.append((np.frombuffer(key, np.int32).tolist(), base, n, hits))
    if wrong:
      self.violation("hits_with_clearing", where, f"{len(wrong)} stored voxels, e.g. (key, hits "
                     f"before, pixels, hits after) {wrong[0]}")
    unread = sum(key in new and key in after["free"] for key in last)
    if unread:
      self.violation("hit_voxel_free", where, f"{unread} voxels the last frame hit are free")
    if int(r["observed"]) != len(new) - len(after["free"]):
      self.violation("observed_count", where, f"{int(r['observed'])} voxels read out, "
                     f"{len(new)} stored, {len(after['free'])} free")
    self.counts["restarted_voxels"] += restarted
    self.counts["free_voxels_at_checks"] += len(after["free"])

  # --- one call through an entry point ---
  def call(self, entry: str, shape, rule_name: str, rng, counted: bool = True,
           force_overfill: bool = False, free_space: bool = False) -> None:
    name, height, width, num_classes, capacity, with_var = shape
    with_var = with_var or NEEDS_VAR[rule_name]
    rule = jf.rules.by_name(rule_name)
    camera = _camera(height, width)
    length = {"frame": 1, "sequence": SEQUENCE_LENGTH, "batch": BATCH_SIZE * BATCH_LENGTH}[entry]
    features = self.features if counted else collections.Counter()
    frames = [make_frame(rng, height, width, num_classes, with_var, features)
              for _ in range(length)]
    if force_overfill:
      for f in frames:
        f[0] = rng.uniform(0.5, 6.0, (height, width)).astype(np.float32)
        f[1] = np.eye(4, dtype=np.float32)
        f[2] = np.full((height, width, num_classes), 1.0 / num_classes, np.float32)
        f[3] = None if f[3] is None else np.full_like(f[2], 0.01)
    key = (entry, name, rule_name, free_space)
    if not force_overfill:
      # Frames that look again from an earlier pose: from the map's anchor (its first frame,
      # while the map lasts) or an earlier frame of the same sequence in this call.
      kept = key in self.maps and self.maps[key][1] > 0 and self.maps[key][3] is not None
      for i, f in enumerate(frames):
        first = (i // BATCH_LENGTH) * BATCH_LENGTH if entry == "batch" else 0
        sources = frames[first:i] + ([self.maps[key][3]] if kept else [])
        if sources and rng.random() < REVISIT_PROBABILITY:
          revisit(rng, f, sources[rng.integers(len(sources))], features)
    reason = None
    if counted and rng.random() < REJECT_PROBABILITY:
      reason = REJECT_REASONS[rng.integers(len(REJECT_REASONS))]
      if reason == "missing_var" and not NEEDS_VAR[rule_name]:
        reason = "pose_nonfinite"
      if reason == "negative_var" and not with_var:
        reason = "k_mismatch"
    if reason is not None:
      # A batch has no map to disagree with: its K mismatch is one sequence against the other.
      group = frames[:BATCH_LENGTH] if entry == "batch" and reason == "k_mismatch" else frames
      inject(rng, group, reason, num_classes)
    where = {"call": self.calls, "entry": entry, "shape": name, "rule": rule_name,
             "free_space": free_space, "expected": reason or "accept",
             "extreme_pose": bool(any(np.abs(f[1][:3, 3]).max() > 1e5 for f in frames))}

    if entry != "batch":
      if key not in self.maps or self.maps[key][1] <= 0:
        voxel_size = 0.02 if force_overfill else float(rng.choice(VOXEL_SIZES))
        state = jf.init_map(capacity=capacity, num_classes=num_classes,
                            voxel_size=voxel_size, rule=rule,
                            free_space=free_space and FREE_SPACE_CONFIG)
        self.maps[key] = [state, int(rng.integers(5, 40)), voxel_size, None]
      state, _, voxel_size, _ = self.maps[key]
      before = snapshot(state)
    else:
      voxel_size = BATCH_VOXEL_SIZE

    def stack(fs):
      var = None if fs[0][3] is None else np.stack([f[3] for f in fs])
      return jf.Frame(np.stack([f[0] for f in fs]), np.stack([f[1] for f in fs]),
                      np.stack([f[2] for f in fs]), var)

    try:
      if entry == "frame":
        result = jf.fuse_frame(state, jf.Frame(*frames[0]), camera, rule)
      elif entry == "sequence":
        result = jf.fuse_sequence(state, stack(frames), camera, rule)
      else:
        sequences = [stack(frames[b * BATCH_LENGTH:(b + 1) * BATCH_LENGTH])
                     for b in range(BATCH_SIZE)]
        batch, mask = jf.stack_sequences(sequences, pad=False)
        result = jf.fuse_batch(batch, camera, rule, capacity=capacity, voxel_size=voxel_size,
                               mask=mask, free_space=free_space and FREE_SPACE_CONFIG)
      jax.block_until_ready(result)
    except (ValueError, TypeError) as err:
      if counted:
        self.calls += 1
        self.frames += length
      if reason is None:
        self.violation("valid_input_refused", where, f"{type(err).__name__}: {err}")
      elif counted:
        self.rejected_calls[reason] += 1
        self.rejected_frames[reason] += length
      return
    except Exception as err:  # pylint: disable=broad-except
      if counted:
        self.calls += 1
        self.frames += length
      self.violation("wrong_exception_type", where, f"{type(err).__name__}: {err}")
      if entry != "batch":
        self.maps.pop(key, None)        # the donated map may be gone
      return
    if counted:
      self.calls += 1
      self.frames += length
      self.counts[f"accepted_calls_{entry}"] += 1
      self.counts["accepted_frames"] += length
      self.counts["accepted_frames_free_space"] += length if free_space else 0
    if reason is not None:
      self.violation(f"accepted_{reason}", where, _describe(frames, reason))

    if entry == "batch":
      for b in range(BATCH_SIZE):
        one = jax.tree.map(lambda x, b=b: x[b], result)
        keys = [valid_keys(f, camera, voxel_size)
                for f in frames[b * BATCH_LENGTH:(b + 1) * BATCH_LENGTH]]
        occupied = int(one.num_occupied)
        self.check_map(one, empty_snapshot(), keys, False, where,
                       read=occupied in (0, capacity))
    else:
      keys = [valid_keys(f, camera, voxel_size) for f in frames]
      occupied = int(result.num_occupied)
      self.check_map(result, before, keys, entry == "frame", where,
                     read=occupied in (0, capacity))
      self.maps[key][0] = result
      self.maps[key][1] -= 1
      if self.maps[key][3] is None:         # the anchor later frames may look again from
        self.maps[key][3] = [frames[0][0].copy(), frames[0][1].copy()]


def _describe(frames, reason: str) -> str:
  """Why an input that should have been refused may have slipped through."""
  probs = np.concatenate([f[2].ravel() for f in frames])
  var = [f[3] for f in frames if f[3] is not None]
  var = np.concatenate([v.ravel() for v in var]) if var else np.zeros(0, np.float32)
  return (f"{reason}: probs has NaN {bool(np.isnan(probs).any())}, min over non-NaN "
          f"{np.nanmin(probs) if probs.size else None}; var has NaN {bool(np.isnan(var).any())},"
          f" min over non-NaN {np.nanmin(var) if var.size else None}")


def schedule():
  """The endless cycle of (entry, shape, rule, free space) calls: every rule through every entry
  point, through all its shapes with free-space clearing off, then all with it on."""
  shapes = {"frame": FRAME_SHAPES, "sequence": SEQUENCE_SHAPES, "batch": BATCH_SHAPES}
  turn = collections.Counter()
  while True:
    for rule_name in RULE_NAMES:
      for entry in SCHEDULE:
        options = [s for s in shapes[entry] if s[5] or not NEEDS_VAR[rule_name]]
        n = turn[entry, rule_name]
        yield entry, options[n % len(options)], rule_name, (n // len(options)) % 2 == 1
        turn[entry, rule_name] += 1


def warm_up(soak: Soak, rng) -> float:
  """Compiles every (entry, shape, rule) once, with a full map (read_map at capacity) and an
  empty one; nothing here is counted."""
  start = time.perf_counter()
  shapes = {"frame": FRAME_SHAPES, "sequence": SEQUENCE_SHAPES, "batch": BATCH_SHAPES}
  for rule_name in RULE_NAMES:
    for entry, options in shapes.items():
      for shape in options:
        if not shape[5] and NEEDS_VAR[rule_name]:
          continue
        for free in FREE_SPACE:
          for _ in range(3 if entry == "frame" else 2):
            soak.call(entry, shape, rule_name, rng, counted=False, force_overfill=True,
                      free_space=free)
          soak.call(entry, shape, rule_name, rng, counted=False, free_space=free)
          # `read_map` of an empty map (all holes, keys past the limit) compiles its own shapes.
          empty = jf.init_map(capacity=shape[4], num_classes=shape[3],
                              rule=jf.rules.by_name(rule_name),
                              free_space=free and FREE_SPACE_CONFIG)
          soak.check_map(empty, empty_snapshot(), [], True, {"call": -1}, read=True)
  soak.maps.clear()
  return time.perf_counter() - start


def run(num_frames: int, seed: int, log=print) -> dict:
  rng = np.random.default_rng(seed)
  load_start = _uptime()
  warm = Soak(seed + 1)                  # its counts are not reported, only its violations
  warm_seconds = warm_up(warm, np.random.default_rng(seed + 1))
  warm_violations = sum(warm.violations.values())
  soak = Soak(seed)
  log(f"warm-up (compiles every shape): {warm_seconds:.1f} s, {warm_violations} violations")
  gc.collect()
  compiles_warm = _COMPILES[0]
  rss = [(0, _rss_mb())]
  start = time.perf_counter()
  next_sample = RSS_EVERY
  for entry, shape, rule_name, free in schedule():
    if soak.frames >= num_frames:
      break
    soak.call(entry, shape, rule_name, rng, free_space=free)
    if soak.frames >= next_sample:
      gc.collect()
      rss.append((soak.frames, _rss_mb()))
      next_sample += RSS_EVERY
      if soak.frames % (4 * RSS_EVERY) < RSS_EVERY:
        log(f"  {soak.frames} frames, {time.perf_counter() - start:.0f} s, RSS "
            f"{rss[-1][1]:.1f} MB, violations {sum(soak.violations.values())}, compilations "
            f"since the warm-up {_COMPILES[0] - compiles_warm}")
  seconds = time.perf_counter() - start
  growth = rss[-1][1] - rss[0][1]
  return {
      "command": "python -m bench.fuzz", "seed": seed, "frames_requested": num_frames,
      "frames": soak.frames, "calls": soak.calls, "seconds": seconds,
      "warm_up_seconds": warm_seconds, "warm_up_violations": warm_violations,
      "warm_up_violation_kinds": dict(warm.violations),
      "jax": jax.__version__, "platform": platform.platform(),
      "device": jax.devices()[0].device_kind,
      "uptime_start": load_start, "uptime_end": _uptime(),
      "shapes": {"frame": FRAME_SHAPES, "sequence": SEQUENCE_SHAPES, "batch": BATCH_SHAPES,
                 "sequence_length": SEQUENCE_LENGTH, "batch_dims": [BATCH_SIZE, BATCH_LENGTH],
                 "batch_voxel_size": BATCH_VOXEL_SIZE, "voxel_sizes": VOXEL_SIZES},
      "rules": list(RULE_NAMES),
      "accepted_frames": soak.counts["accepted_frames"],
      "accepted_calls": {e: soak.counts[f"accepted_calls_{e}"] for e in ("frame", "sequence",
                                                                          "batch")},
      "rejected_frames": dict(soak.rejected_frames), "rejected_calls": dict(soak.rejected_calls),
      "maps_checked": soak.counts["maps_checked"], "read_map_calls": soak.counts["read_map_calls"],
      "free_space": {name: soak.counts[name] for name in (
          "accepted_frames_free_space", "maps_checked_free_space", "free_voxels_at_checks",
          "restarted_voxels")},
      "overfill": dict(soak.overfill), "features": dict(sorted(soak.features.items())),
      "extremes": {k: float(v) for k, v in soak.extremes.items()},
      "violations": dict(soak.violations), "violation_total": sum(soak.violations.values()),
      "violation_examples": soak.examples,
      "violations_by_entry_and_pose": [
          {"kind": k, "entry": e, "extreme_pose": x, "count": n}
          for (k, e, x), n in sorted(soak.violations_by_call.items(), key=str)],
      "rss_mb": rss, "rss_growth_mb": growth,
      "compiles_in_warm_up": compiles_warm, "compiles_after_warm_up": _COMPILES[0] - compiles_warm,
  }


def table(r: dict) -> str:
  rejected = ", ".join(f"{k} {v}" for k, v in sorted(r["rejected_frames"].items()))
  calls = ", ".join(f"{k} {v}" for k, v in sorted(r["rejected_calls"].items()))
  o = r["overfill"]
  lines = [
      f"{r['frames']} frames in {r['calls']} calls ({r['seconds']:.0f} s after a "
      f"{r['warm_up_seconds']:.0f} s warm-up), seed {r['seed']}, rules: "
      + ", ".join(r["rules"]), "",
      "| count | value |", "|---|---|",
      f"| frames accepted | {r['accepted_frames']} (calls: fuse_frame "
      f"{r['accepted_calls']['frame']}, fuse_sequence {r['accepted_calls']['sequence']}, "
      f"fuse_batch {r['accepted_calls']['batch']}) |",
      f"| frames rejected (ValueError/TypeError), by reason | "
      f"{sum(r['rejected_frames'].values())}: {rejected} |",
      f"| calls rejected, by reason | {sum(r['rejected_calls'].values())}: {calls} |",
      f"| maps checked (read_map on empty/full maps) | {r['maps_checked']} "
      f"({r['read_map_calls']}) |",
      f"| with free-space clearing: frames accepted / maps checked / free voxels summed over "
      f"the checks / voxels restarted | {r['free_space']['accepted_frames_free_space']} / "
      f"{r['free_space']['maps_checked_free_space']} / "
      f"{r['free_space']['free_voxels_at_checks']} / {r['free_space']['restarted_voxels']} |",
      f"| calls that overfilled a map (new valid voxels > free slots) / voxels dropped there | "
      f"{o.get('overfilled_maps', 0)} / {o.get('dropped_in_overfilled', 0)} |",
      f"| calls that dropped before the map was full (probe bound) / voxels dropped | "
      f"{o.get('maps_dropping_before_full', 0)} / {o.get('dropped_before_full', 0)} |",
      f"| violations | **{r['violation_total']}** "
      + (f"({', '.join(f'{k} {v}' for k, v in sorted(r['violations'].items()))})"
         if r["violations"] else "") + " |",
      f"| RSS first → last sample (every {RSS_EVERY} frames) | {r['rss_mb'][0][1]:.1f} → "
      f"{r['rss_mb'][-1][1]:.1f} MB (growth {r['rss_growth_mb']:+.1f} MB; min "
      f"{min(m for _, m in r['rss_mb']):.1f}, max {max(m for _, m in r['rss_mb']):.1f}) |",
      f"| XLA compilations in the warm-up / after it | {r['compiles_in_warm_up']} / "
      f"{r['compiles_after_warm_up']} |",
      f"| worst posterior max − 1 / sum error / entropy min | "
      f"{r['extremes']['posterior_max'] - 1:.2e} / {r['extremes']['sum_error']:.2e} / "
      f"{r['extremes']['entropy_min']:.2e} |",
  ]
  lines += ["", "| violation | entry | extreme pose in the call | count |", "|---|---|---|---|"]
  lines += [f"| {v['kind']} | {v['entry']} | {v['extreme_pose']} | {v['count']} |"
            for v in r["violations_by_entry_and_pose"]]
  for ex in r["violation_examples"]:
    lines.append(f"\n- {ex}")
  return "\n".join(lines)


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(prog="python -m bench.fuzz",
                                   description=__doc__.split("\n")[0])
  parser.add_argument("--frames", type=int, default=10**4, help="frames in all (default 10⁴)")
  parser.add_argument("--seed", type=int, default=0)
  parser.add_argument("--quick", action="store_true", help="1 000 frames")
  parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results"))
  args = parser.parse_args(argv)
  num_frames = 1000 if args.quick else args.frames
  result = run(num_frames, args.seed, log=lambda s: print(s, flush=True))
  out = pathlib.Path(args.out)
  out.mkdir(parents=True, exist_ok=True)
  (out / "fuzz.json").write_text(json.dumps(result, indent=1, default=str))
  print(table(result))
  print(f"\nwrote {out / 'fuzz.json'}")


if __name__ == "__main__":
  main()
