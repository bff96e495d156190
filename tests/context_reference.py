"""A slow, obvious NumPy version of the per-pixel context features (docs/equations.md §2.5),
written pixel by pixel from the equations, independent of `jaxfusion.context`."""

import numpy as np

TAU, D, WIN = 0.05, 16, 5


def _valid(z):
  return np.isfinite(z) and z > 0


def _break(depth, a, b):
  za, zb = depth[a], depth[b]
  if not (_valid(za) and _valid(zb)):
    return True
  return abs(za - zb) > TAU * min(za, zb)


def _neighbours(h, w, v, u):
  for dv, du in ((0, 1), (0, -1), (1, 0), (-1, 0)):
    if 0 <= v + dv < h and 0 <= u + du < w:
      yield v + dv, u + du


def _distance(edges):
  h, w = edges.shape
  ys, xs = np.nonzero(edges)
  out = np.full((h, w), float(D))
  for v in range(h):
    for u in range(w):
      if len(ys):
        out[v, u] = min(D, np.min(np.maximum(np.abs(ys - v), np.abs(xs - u))))
  return out


def _point(depth, cam, v, u):
  fx, fy, cx, cy = cam
  z = depth[v, u]
  return np.array([z * (u - cx) / fx, z * (v - cy) / fy, z], np.float64)


def context(depth, probs, cam, names, rgb=None):
  """`(H, W, F)` float64 features; `cam = (fx, fy, cx, cy)`."""
  depth = np.asarray(depth, np.float64)
  h, w = depth.shape
  fx, fy, cx, cy = cam
  ok = np.isfinite(depth) & (depth > 0)
  z = np.where(ok, depth, 0.0)
  out = {"depth": z}
  edge = np.zeros((h, w), bool)
  for v in range(h):
    for u in range(w):
      edge[v, u] = any(_break(z, (v, u), q) for q in _neighbours(h, w, v, u))
  out["depth_edge"] = _distance(edge)
  inc = np.ones((h, w))
  for v in range(h):
    for u in range(w):
      if not ok[v, u]:
        continue
      tangents = []
      for plus, minus in (((v, u + 1), (v, u - 1)), ((v + 1, u), (v - 1, u))):
        fine = [0 <= q[0] < h and 0 <= q[1] < w and not _break(z, (v, u), q)
                for q in (plus, minus)]
        if fine[0] and fine[1]:
          tangents.append(_point(z, cam, *plus) - _point(z, cam, *minus))
        elif fine[0]:
          tangents.append(_point(z, cam, *plus) - _point(z, cam, v, u))
        elif fine[1]:
          tangents.append(_point(z, cam, v, u) - _point(z, cam, *minus))
      if len(tangents) < 2:
        continue
      n = np.cross(tangents[0], tangents[1])
      x = _point(z, cam, v, u)
      if np.linalg.norm(n) > 0:
        inc[v, u] = min(1.0, abs(n @ x) / (np.linalg.norm(n) * np.linalg.norm(x)))
  out["incidence"] = inc
  p = np.asarray(probs, np.float64)
  p = np.where(np.isfinite(p), np.maximum(p, 0.0), 1.0 / p.shape[-1])
  label = np.argmax(p, -1)
  ledge = np.zeros((h, w), bool)
  for v in range(h):
    for u in range(w):
      ledge[v, u] = any(label[q] != label[v, u] for q in _neighbours(h, w, v, u))
  out["label_edge"] = _distance(ledge)
  r = lambda u, v: np.hypot((u - cx) / fx, (v - cy) / fy)
  r_max = max(r(u, v) for u in (0, w - 1) for v in (0, h - 1))
  out["radius"] = np.array([[r(u, v) / r_max for u in range(w)] for v in range(h)])
  if rgb is not None:
    c = np.asarray(rgb, np.float64)
    if np.asarray(rgb).dtype == np.uint8:
      c = c / 255.0
    c = np.clip(c, 0, 1)
    lum = c[..., 0] * 0.299 + c[..., 1] * 0.587 + c[..., 2] * 0.114
    at = lambda v, u: lum[min(max(v, 0), h - 1), min(max(u, 0), w - 1)]
    lap = np.array([[at(v, u + 1) + at(v, u - 1) + at(v + 1, u) + at(v - 1, u) - 4 * lum[v, u]
                     for u in range(w)] for v in range(h)])
    top = c.max(-1)
    clip = ((top >= 250 / 255) | (top <= 5 / 255)).astype(float)
    half = WIN // 2

    def wmean(x, v, u):
      return x[max(v - half, 0):v + half + 1, max(u - half, 0):u + half + 1].mean()
    out["sharpness"] = np.array([[np.sqrt(wmean(lap**2, v, u)) for u in range(w)]
                                 for v in range(h)])
    out["luminance"] = np.array([[wmean(lum, v, u) for u in range(w)] for v in range(h)])
    out["clipped"] = np.array([[wmean(clip, v, u) for u in range(w)] for v in range(h)])
  return np.stack([out[n] for n in names], -1)
