"""A slow, obvious NumPy reference of docs/equations.md (§1–§3): a dict keyed by voxel coordinates,
float64, plain Python loops over pixels and voxels. Written from the spec, not from the engine."""

import math
from collections import defaultdict

import numpy as np

TINY = float(np.finfo(np.float32).tiny)   # docs/equations.md §5.1: log(max(p, tiny))


def pixel_points(depth, T_world_cam, fx, fy, cx, cy):
  """Yields ((v, u), world point) of every valid pixel, in float64."""
  T = np.asarray(T_world_cam, np.float64)
  H, W = depth.shape
  for v in range(H):
    for u in range(W):
      d = float(depth[v, u])
      if not math.isfinite(d) or d <= 0:
        continue
      p_cam = np.array([d * (u - cx) / fx, d * (v - cy) / fy, d])
      yield (v, u), T[:3, :3] @ p_cam + T[:3, 3]


def per_class_regularize(p, beta):
  """docs/equations.md §3.7, one pixel: `p̃_i = ((1−β_i) p_i + β_i/K) / Z`, `Z = Σ_i (…)`; uniform
  if Z = 0."""
  K = len(p)
  mixed = np.array([(1.0 - float(beta[i])) * p[i] + float(beta[i]) / K for i in range(K)])
  Z = sum(mixed)
  return mixed / Z if Z > 0 else np.full(K, 1.0 / K)


def sigmoid(x):
  return 1.0 / (1.0 + math.exp(-x)) if x >= 0 else math.exp(x) / (1.0 + math.exp(x))


def learned_features(p, s, eps):
  """docs/equations.md §3.9: the six features of one pixel, written out one by one."""
  K = len(p)
  order = sorted(range(K), key=lambda i: -p[i])
  pred = int(np.argmax(p))                  # first of equal maxima, as argmax
  top, second = p[order[0]], p[order[1]]
  entropy = -sum(q * math.log(max(q, TINY)) for q in p) / math.log(K)
  v_pred = min(max(s[pred], 0.0), 0.25)
  alpha_pred = -math.log(v_pred + eps) / 10.0
  sqrt_sum_var = math.sqrt(sum(min(max(x, 0.0), 0.25) for x in s) + 1e-12)
  bound = p[pred] * (1.0 - p[pred])
  rel = min(v_pred / bound, 1.0) if bound > 0 else 0.0
  return np.array([top, top - second, entropy, alpha_pred, sqrt_sum_var, rel])


# docs/equations.md §3.9: the fixed scales of the context features in the learned weight.
CONTEXT_SCALE = {"depth": 0.25, "incidence": 1.0, "depth_edge": 1 / 16, "label_edge": 1 / 16,
                 "radius": 1.0, "sharpness": 4.0, "luminance": 1.0, "clipped": 1.0}


class ReferenceMap:
  """One map under one rule, by docs/equations.md §3. `rule` is one of the six paper names, or
  "learned" (§3.9, its parameters in `learned`). `beta`, `eps` and `alpha0` may be scalars or
  per-class sequences of length K (§3.7)."""

  def __init__(self, rule, num_classes, voxel_size, *, beta=0.3, eps=1e-12,
               alpha0=-math.log(1e-3), aggregate="sum", learned=None, context=(),
               glfs=None):
    self.rule, self.K, self.voxel_size = rule, num_classes, voxel_size
    as_param = lambda x: float(x) if np.ndim(x) == 0 else np.asarray(x, np.float64)
    self.beta, self.eps, self.alpha0 = as_param(beta), as_param(eps), as_param(alpha0)
    self.aggregate = aggregate
    self.learned = {k: np.asarray(v, np.float64) for k, v in (learned or {}).items()}
    self.context = tuple(context)          # the learned rule's context names (§2.5)
    self.glfs = glfs                       # (table, depth_edges, angle_edges) for "glfs"
    self.voxels = {}

  def _new_voxel(self):
    K = self.K
    return {"score": np.zeros(K), "logp": np.full(K, -math.log(K)),
            "alpha_bar": np.full(K, self.alpha0), "hits": 0, "frames": 0}

  def fuse(self, depth, T_world_cam, probs, var, fx, fy, cx, cy, ctx=None):
    """`ctx`: `(H, W, F)` per-pixel context features in the rule's order (§2.5), or None."""
    groups = defaultdict(list)
    contexts = defaultdict(list)
    for (v, u), p_world in pixel_points(depth, T_world_cam, fx, fy, cx, cy):
      p = np.asarray(probs[v, u], np.float64)
      s = np.zeros(self.K) if var is None else np.asarray(var[v, u], np.float64)
      if not (np.all(np.isfinite(p)) and np.all(np.isfinite(s))):
        continue
      key = tuple(int(k) for k in np.floor(p_world / self.voxel_size))
      groups[key].append((p, s))
      contexts[key].append(None if ctx is None else np.asarray(ctx[v, u], np.float64))
    for key, pixels in groups.items():
      voxel = self.voxels.setdefault(key, self._new_voxel())
      self._update(voxel, pixels, contexts[key])
      voxel["hits"] += len(pixels)
      voxel["frames"] += 1

  def _reduce(self, values):
    total = np.sum(values, axis=0)
    return total / len(values) if self.aggregate == "mean" else total

  def _update(self, voxel, pixels, contexts):
    K, rule = self.K, self.rule
    if rule == "sum_probs":
      voxel["score"] += self._reduce([p for p, _ in pixels])
      return
    if rule == "sum_labels":
      voxel["score"] += self._reduce([np.eye(K)[int(np.argmax(p))] for p, _ in pixels])
      return
    if rule == "learned":
      self._update_learned(voxel, pixels, contexts)
      return
    if rule == "family":
      self._update_family(voxel, pixels, contexts)
      return
    if rule == "glfs":   # §3.10
      table, depth_edges, angle_edges = self.glfs
      total = []
      for (p, _), c in zip(pixels, contexts):
        d = int(np.sum(np.asarray(depth_edges) <= c[0]))
        a = int(np.sum(np.asarray(angle_edges) <= c[1]))
        total.append(table[int(np.argmax(p)), d, a] * np.log(np.maximum(p, TINY)))
      logp = voxel["logp"] + self._reduce(total)
      voxel["logp"] = logp - np.log(np.sum(np.exp(logp - logp.max()))) - logp.max()
      return
    if rule in ("robust_r", "robust_dr") and np.ndim(self.beta) == 0:
      pixels = [((1 - self.beta) * p + self.beta / K, s) for p, s in pixels]
    elif rule in ("robust_r", "robust_dr"):   # docs/equations.md §3.7: per-class β, over Z_j
      pixels = [(per_class_regularize(p, self.beta), s) for p, s in pixels]
    logs = [np.log(np.maximum(p, TINY)) for p, _ in pixels]
    if rule in ("bayes", "robust_r"):
      logp = voxel["logp"] + self._reduce(logs)
    else:  # robust_d, robust_dr
      alphas = [-np.log(np.clip(s, 0.0, 0.25) + self.eps) for _, s in pixels]
      prev = voxel["alpha_bar"]
      new = np.maximum(prev, np.max(alphas, axis=0))
      weighted = self._reduce([a * l for a, l in zip(alphas, logs)])
      logp = prev / new * voxel["logp"] + weighted / new
      voxel["alpha_bar"] = new
    voxel["logp"] = logp - np.log(np.sum(np.exp(logp - logp.max()))) - logp.max()

  def _update_learned(self, voxel, pixels, contexts):
    """docs/equations.md §3.9, one voxel and one frame."""
    K, hp = self.K, self.learned
    theta, bias, mix, gate = hp["theta"], hp["bias"], float(hp["mix"]), hp["gate"]
    beta = np.broadcast_to(self.beta, (K,))
    plain, weighted, alphas = [], [], []
    for (p, s), c in zip(pixels, contexts):
      pred = int(np.argmax(p))
      th = theta[pred] if theta.ndim == 2 else theta
      b = float(bias[pred]) if bias.ndim == 1 else float(bias)
      z = float(th @ learned_features(p, s, self.eps)) + b
      if self.context:
        scale = np.array([CONTEXT_SCALE[n] for n in self.context])
        ct = hp["context_theta"]
        z += float((ct[pred] if ct.ndim == 2 else ct) @ (scale * c))
      w = sigmoid(z)
      log_pt = np.log(np.maximum(per_class_regularize(p, beta) if np.ndim(self.beta)
                                 else (1 - self.beta) * p + self.beta / K, TINY))
      alpha = -np.log(np.clip(s, 0.0, 0.25) + self.eps)
      plain.append(w * log_pt)
      weighted.append(w * alpha * log_pt)
      alphas.append(alpha)
    prev = voxel["alpha_bar"]
    new = np.maximum(prev, np.max(alphas, axis=0))
    keep = (1 - mix) + mix * prev / new
    obs = (1 - mix) * self._reduce(plain) + mix * self._reduce(weighted) / new
    prior = np.exp(voxel["logp"] - voxel["logp"].max())
    prior /= prior.sum()
    soft = np.exp(obs - obs.max())
    soft /= soft.sum()
    spread = -sum(q * math.log(max(q, TINY)) for q in prior) / math.log(K)
    logit = gate[0] + gate[1] * float(prior @ soft) + gate[2] * spread
    if len(gate) == 5:
      mid = 0.5 * (soft + prior)
      kl = lambda a: sum(x * (math.log(max(x, TINY)) - math.log(max(m, TINY)))
                         for x, m in zip(a, mid) if x > 0)
      js = min(max(0.5 * (kl(soft) + kl(prior)) / math.log(2), 0.0), 1.0)
      logit += gate[3] * js + gate[4] * math.log1p(voxel["frames"]) / math.log(33.0)
    g = sigmoid(logit)
    logp = keep * voxel["logp"] + g * obs
    voxel["logp"] = logp - np.log(np.sum(np.exp(logp - logp.max()))) - logp.max()
    voxel["alpha_bar"] = new

  def _update_family(self, voxel, pixels, contexts):
    """docs/equations.md §3.11, one voxel and one frame: `self.learned` holds the family's
    parameters (the terms present are the keys given), `self.context` the rule's context names
    (the weights read the first F of them, F the width of their context weights)."""
    K, hp = self.K, self.learned
    row = lambda x, pred, per_class_ndim: x[pred] if x.ndim == per_class_ndim else x
    eps = float(hp.get("eps", 1e-12))
    width = next((hp[n].shape[-1] for n in ("context_weights", "context_theta") if n in hp), 0)
    names = self.context[:width]
    scale = np.array([CONTEXT_SCALE[n] for n in names])
    plain, weighted, alphas = [], [], []
    for (p, s), c in zip(pixels, contexts):
      pred = int(np.argmax(p))
      phi = learned_features(p, s, eps)
      psi = None if not names else scale * np.asarray(c[:width])
      w = 1.0
      if "table" in hp:
        z_ = c[self.context.index("depth")]
        cos = c[self.context.index("incidence")]
        w *= hp["table"][pred, int(np.sum(hp["depth_edges"] <= z_)),
                         int(np.sum(hp["angle_edges"] <= cos))]
      if "moment_weights" in hp or "context_weights" in hp:
        z = 0.0
        if "moment_weights" in hp:
          z += float(row(hp["moment_weights"], pred, 2) @ phi)
        if "context_weights" in hp:
          z += float(row(hp["context_weights"], pred, 2) @ psi)
        w *= math.exp(min(max(z, -15.0), 15.0))
      if "theta" in hp:
        z = float(row(hp["theta"], pred, 2) @ phi) + float(row(hp["bias"], pred, 1))
        if "context_theta" in hp:
          z += float(row(hp["context_theta"], pred, 2) @ psi)
        w *= sigmoid(z)
      if "beta" in hp:
        p = per_class_regularize(p, np.broadcast_to(hp["beta"], (K,)))
      log_pt = np.log(np.maximum(p, TINY))
      alpha = -np.log(np.clip(s, 0.0, 0.25) + eps)
      plain.append(w * log_pt)
      weighted.append(w * alpha * log_pt)
      alphas.append(alpha)
    if "mix" in hp:
      mix = float(hp["mix"])
      prev = voxel["alpha_bar"]
      new = np.maximum(prev, np.max(alphas, axis=0))
      keep = (1 - mix) + mix * prev / new
      obs = (1 - mix) * self._reduce(plain) + mix * self._reduce(weighted) / new
      voxel["alpha_bar"] = new
    else:
      keep, obs = 1.0, self._reduce(plain)
    g = 1.0
    if "gate" in hp:
      gate = hp["gate"]
      prior = np.exp(voxel["logp"] - voxel["logp"].max())
      prior /= prior.sum()
      soft = np.exp(obs - obs.max())
      soft /= soft.sum()
      spread = -sum(q * math.log(max(q, TINY)) for q in prior) / math.log(K)
      logit = gate[0] + gate[1] * float(prior @ soft) + gate[2] * spread
      if len(gate) == 5:
        mid = 0.5 * (soft + prior)
        kl = lambda a: sum(x * (math.log(max(x, TINY)) - math.log(max(m, TINY)))
                           for x, m in zip(a, mid) if x > 0)
        js = min(max(0.5 * (kl(soft) + kl(prior)) / math.log(2), 0.0), 1.0)
        logit += gate[3] * js + gate[4] * math.log1p(voxel["frames"]) / math.log(33.0)
      g = sigmoid(logit)
    logp = keep * voxel["logp"] + g * obs
    voxel["logp"] = logp - np.log(np.sum(np.exp(logp - logp.max()))) - logp.max()

  def read(self):
    """Same layout as jaxfusion.read_map, sorted by coordinates."""
    keys = sorted(self.voxels)
    out = {"coords": np.array(keys, np.int64).reshape(-1, 3), "posterior": [], "hits": [],
           "confidence": []}
    for key in keys:
      voxel = self.voxels[key]
      if self.rule in ("sum_probs", "sum_labels"):
        total = voxel["score"].sum()
        post = voxel["score"] / total if total > 0 else np.full(self.K, 1.0 / self.K)
      else:
        post = np.exp(voxel["logp"])
        post = post / post.sum()
      out["posterior"].append(post)
      out["hits"].append(voxel["hits"])
      out["confidence"].append(voxel["alpha_bar"])
    out["posterior"] = np.array(out["posterior"]).reshape(-1, self.K)
    out["hits"] = np.array(out["hits"], np.int64)
    out["confidence"] = np.array(out["confidence"]).reshape(-1, self.K)
    out["labels"] = np.argmax(out["posterior"], axis=1) if keys else np.zeros(0, int)
    return out
