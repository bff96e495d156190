"""The same fusion in vectorised NumPy: the best NumPy can do, as a speed yardstick.

Not the slow dict-of-voxels oracle of `tests/reference.py`: a frame is one pass of array
operations. Pixels are grouped by one `np.unique` over their keys packed into one int64 (a sort),
per-voxel sums and maxes are `np.add.reduceat` / `np.maximum.reduceat` over the sorted pixels,
and the map is a Python dict from packed key to a row of dense `(C, K)` arrays (looked up once
per voxel per frame, which is the fastest map NumPy offers without a C extension). It follows
docs/equations.md for all six rules and both aggregation modes.

Shape legend: H×W pixels, N = H·W, K classes, U voxels in a frame, C slots.
"""

import numpy as np

_TINY = np.float32(np.finfo(np.float32).tiny)
_OFFSET = np.int64(2**20)   # keys packed as 21 bits per axis (±1 M voxels, ±100 km at 0.1 m)
RULES = ("sum_probs", "sum_labels", "bayes", "robust_r", "robust_d", "robust_dr")


def _safe_log(p):
  return np.log(np.maximum(p, _TINY))


class NumpyMap:
  """A semantic voxel map fused with NumPy. Rows are float32 `(C, K)` arrays grown on demand.

  Args:
    num_classes: K.
    rule: one of `RULES`.
    voxel_size: voxel edge in metres.
    beta, eps, alpha0: the robust rules' hyperparameters (docs/equations.md §3.8 defaults).
    aggregate: "sum" (the paper's Σ_j) or "mean".
    capacity: initial number of rows (the arrays double when full).
  """

  def __init__(self, num_classes, rule, *, voxel_size=0.1, beta=0.3, eps=1e-12,
               alpha0=-np.log(1e-3), aggregate="sum", capacity=2**16):
    if rule not in RULES:
      raise ValueError(f"unknown rule {rule!r}")
    self.k = num_classes
    self.rule = rule
    self.voxel_size = np.float32(voxel_size)
    self.beta, self.eps, self.alpha0 = np.float32(beta), np.float32(eps), np.float32(alpha0)
    self.aggregate = aggregate
    self.index = {}
    self.size = 0
    self.keys = np.zeros((capacity, 3), np.int64)
    self.hits = np.zeros(capacity, np.int64)
    prior = 0.0 if rule.startswith("sum") else -np.log(num_classes)
    self._prior = np.float32(prior)
    self.score = np.full((capacity, num_classes), self._prior, np.float32)
    self.alpha_bar = np.full((capacity, num_classes), self.alpha0, np.float32)

  def _grow(self, needed):
    cap = self.score.shape[0]
    while cap < needed:
      cap *= 2
    if cap == self.score.shape[0]:
      return
    extra = cap - self.score.shape[0]
    self.keys = np.concatenate([self.keys, np.zeros((extra, 3), np.int64)])
    self.hits = np.concatenate([self.hits, np.zeros(extra, np.int64)])
    self.score = np.concatenate([self.score, np.full((extra, self.k), self._prior, np.float32)])
    self.alpha_bar = np.concatenate(
        [self.alpha_bar, np.full((extra, self.k), self.alpha0, np.float32)])

  def _slots(self, packed, group_keys):
    """Slots of the frame's packed keys, creating rows for new voxels."""
    index = self.index
    slots = np.fromiter((index.get(p, -1) for p in packed.tolist()), np.int64, len(packed))
    new = np.nonzero(slots < 0)[0]
    if len(new):
      self._grow(self.size + len(new))
      new_slots = np.arange(self.size, self.size + len(new))
      index.update(zip(packed[new].tolist(), new_slots.tolist()))
      self.keys[new_slots] = group_keys[new]
      slots[new] = new_slots
      self.size += len(new)
    return slots

  def fuse(self, depth, T_world_cam, probs, var, camera):
    """Fuses one frame (NumPy arrays: depth `(H, W)`, T `(4, 4)`, probs/var `(H, W, K)`)."""
    height, width = depth.shape
    n = height * width
    k = self.k
    depth = np.asarray(depth, np.float32)
    T = np.asarray(T_world_cam, np.float32)
    u = np.arange(width, dtype=np.float32)[None, :]
    v = np.arange(height, dtype=np.float32)[:, None]
    x = depth * ((u - np.float32(camera.cx)) / np.float32(camera.fx))
    y = depth * ((v - np.float32(camera.cy)) / np.float32(camera.fy))
    with np.errstate(invalid="ignore", over="ignore"):
      scaled = [np.floor((x * T[i, 0] + y * T[i, 1] + depth * T[i, 2] + T[i, 3])
                         / self.voxel_size).reshape(n) for i in range(3)]
      valid = (depth.reshape(n) > 0)
      for s in scaled:
        valid &= np.isfinite(s) & (np.abs(s) < _OFFSET)
    probs = np.asarray(probs, np.float32).reshape(n, k)
    valid &= np.isfinite(probs).all(axis=1)
    if var is not None:
      var = np.asarray(var, np.float32).reshape(n, k)
      valid &= np.isfinite(var).all(axis=1)
    idx = np.nonzero(valid)[0]
    if len(idx) == 0:
      return
    keys = np.stack([s[idx].astype(np.int64) for s in scaled], axis=-1)
    packed = ((keys[:, 0] + _OFFSET) << 42) | ((keys[:, 1] + _OFFSET) << 21) | (keys[:, 2] +
                                                                                _OFFSET)
    order = np.argsort(packed, kind="stable")
    packed_sorted = packed[order]
    starts = np.concatenate([[0], np.nonzero(packed_sorted[1:] != packed_sorted[:-1])[0] + 1])
    counts = np.diff(np.append(starts, len(order))).astype(np.float32)
    pix = idx[order]
    p = np.maximum(probs[pix], 0.0)
    slots = self._slots(packed_sorted[starts], keys[order[starts]])
    self.hits[slots] += counts.astype(np.int64)
    rule = self.rule

    def seg_sum(t):
      s = np.add.reduceat(t, starts, axis=0)
      return s / counts[:, None] if self.aggregate == "mean" else s

    if rule == "sum_probs":
      self.score[slots] += seg_sum(p)
      return
    if rule == "sum_labels":
      votes = np.zeros((len(p), k), np.float32)
      votes[np.arange(len(p)), np.argmax(p, axis=1)] = 1.0
      self.score[slots] += seg_sum(votes)
      return
    if rule in ("robust_r", "robust_dr"):
      p = (1.0 - self.beta) * p + self.beta / k
    loglik = _safe_log(p)
    if rule in ("bayes", "robust_r"):
      logp = self.score[slots] + seg_sum(loglik)
    else:
      alpha = -np.log(np.clip(var[pix], 0.0, 0.25) + self.eps)
      alpha_max = np.maximum.reduceat(alpha, starts, axis=0)
      alpha_prev = self.alpha_bar[slots]
      alpha_bar = np.maximum(alpha_prev, alpha_max)
      safe = np.where(alpha_bar > 0, alpha_bar, 1.0)
      logp = (alpha_prev / safe) * self.score[slots] + seg_sum(alpha * loglik) / safe
      self.alpha_bar[slots] = alpha_bar
    m = logp.max(axis=1, keepdims=True)
    self.score[slots] = logp - (m + np.log(np.exp(logp - m).sum(axis=1, keepdims=True)))

  def posteriors(self):
    """`(keys (U, 3) int64, posterior (U, K) float32)` of every stored voxel."""
    score = self.score[:self.size]
    if self.rule.startswith("sum"):
      total = score.sum(axis=1, keepdims=True)
      post = np.where(total > 0, score / np.where(total > 0, total, 1.0), 1.0 / self.k)
    else:
      e = np.exp(score - score.max(axis=1, keepdims=True))
      post = e / e.sum(axis=1, keepdims=True)
    return self.keys[:self.size], post.astype(np.float32)
