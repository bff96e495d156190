"""Per-pixel context features of a frame, for rules that ask for them (docs/equations.md §2.5).

A rule names what it reads in its static `context` tuple (names from `FEATURES`); `fuse_frame`
then calls `pixel_context` once per frame and hands each pixel's `(F,)` vector to the rule's
`observe`. Everything here is computed from the frame itself: depth, camera, the predicted labels
(argmax of `probs`) and the colour image. Rules that ask for nothing never reach this module.

Shape legend: H×W pixels, K classes, F requested features.
"""

from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import camera as camera_lib

# Every feature, in a fixed order (a rule's `context` may name any of them, in any order).
FEATURES = ("depth", "incidence", "depth_edge", "label_edge", "radius", "sharpness",
            "luminance", "clipped")
# Features that read the colour image (`Frame.rgb`).
IMAGE_FEATURES = ("sharpness", "luminance", "clipped")
# Relative depth step between 4-neighbours that counts as a discontinuity (τ).
JUMP = 0.05
# Cap of the edge distances, in pixels (D).
MAX_EDGE_DISTANCE = 16
# Side of the window of the image features.
WINDOW = 5
# Channel levels (of 255) at and beyond which a pixel counts as clipped.
CLIP_HIGH, CLIP_LOW = 250.0 / 255.0, 5.0 / 255.0


def check_names(names: Sequence[str]) -> tuple:
  """`names` as a tuple, or ValueError naming the unknown or repeated ones."""
  names = tuple(names)
  unknown = [n for n in names if n not in FEATURES]
  if unknown:
    raise ValueError(f"unknown context features {unknown}; the features are "
                     f"{', '.join(FEATURES)}")
  if len(set(names)) != len(names):
    raise ValueError(f"context features must not repeat; got {list(names)}")
  return names


def needs_rgb(names: Sequence[str]) -> bool:
  """True if any of `names` reads the colour image."""
  return any(n in IMAGE_FEATURES for n in names)


def _shift(x, du: int, dv: int, fill):
  """`x` moved so that out[v, u] = x[v + dv, u + du], `fill` outside the image."""
  h, w = x.shape
  padded = jnp.pad(x, ((1, 1), (1, 1)), constant_values=fill)
  return jax.lax.dynamic_slice(padded, (1 + dv, 1 + du), (h, w))


_NEIGHBOURS = ((1, 0), (-1, 0), (0, 1), (0, -1))


def _inside(shape, du: int, dv: int):
  """`(H, W) bool`: the neighbour (du, dv) of each pixel lies inside the image."""
  return _shift(jnp.ones(shape, bool), du, dv, False)


def _discontinuity(depth, ok, du, dv):
  """`(H, W) bool`: a discontinuity between each pixel and its neighbour (du, dv) (False where
  the neighbour lies outside the image)."""
  inside = _inside(depth.shape, du, dv)
  z_q = _shift(depth, du, dv, 0.0)
  ok_q = _shift(ok, du, dv, False)
  jump = jnp.abs(depth - z_q) > JUMP * jnp.minimum(depth, z_q)
  return inside & (~ok | ~ok_q | jump)


def _dilate(reach):
  """`(H, W) bool`: True where a pixel of the 3×3 window at each pixel is (cut to the image),
  as two 3-wide ORs of shifted copies: XLA fuses these into elementwise loops, where the 3×3
  `reduce_window` max it replaces cost more than the rest of `pixel_context` (bench/RESULTS.md,
  "Per-pixel context": 87.8 → 28.7 ms for every feature at 640×480)."""
  for axis in (0, 1):
    n = reach.shape[axis]
    pad = [(0, 0), (0, 0)]
    pad[axis] = (1, 1)
    padded = jnp.pad(reach, pad, constant_values=False)
    reach = (reach | jax.lax.slice_in_dim(padded, 0, n, axis=axis)
             | jax.lax.slice_in_dim(padded, 2, n + 2, axis=axis))
  return reach


def _edge_distance(edges):
  """Capped Chebyshev distance to the nearest True pixel (`D` where none is nearer): the number
  of 3×3 dilations of the edges, of the first D, that do not reach a pixel yet."""
  def step(_, carry):
    dist, reach = carry
    return dist + jnp.where(reach, 0.0, 1.0), _dilate(reach)

  # A loop, not 16 unrolled dilations: unrolled, the fused programs that read the context
  # compiled 12 s longer (tests/engine/test_context.py's random frames: 16 s against 4 s).
  dist, _ = jax.lax.fori_loop(0, MAX_EDGE_DISTANCE, step,
                              (jnp.zeros(edges.shape, jnp.float32), edges))
  return dist


def _window_count(shape) -> np.ndarray:
  """`(H, W) float32`: how many pixels of the WINDOW×WINDOW window at each pixel lie inside the
  image. It depends on the shape only, so it is a NumPy constant: summing a window over an array
  of ones in the program made XLA constant-fold a reduce-window (20 s of compile at 640×480)."""
  r = WINDOW // 2

  def per_axis(n):
    i = np.arange(n)
    return np.minimum(i, r) + np.minimum(n - 1 - i, r) + 1

  return np.outer(per_axis(shape[0]), per_axis(shape[1])).astype(np.float32)


def _window_mean(x):
  """Mean of `x` over the WINDOW×WINDOW window at each pixel, cut to the image."""
  dims, strides = (WINDOW, WINDOW), (1, 1)
  total = jax.lax.reduce_window(x, 0.0, jax.lax.add, dims, strides, "SAME")
  return total / _window_count(x.shape)


def _incidence(points, depth, ok, breaks):
  """`cos θ` between the depth normal and the viewing ray (docs/equations.md §2.5)."""
  def tangent(axis_plus, axis_minus):
    (du_p, dv_p), (du_m, dv_m) = axis_plus, axis_minus
    x_p = jnp.stack([_shift(points[..., c], du_p, dv_p, 0.0) for c in range(3)], -1)
    x_m = jnp.stack([_shift(points[..., c], du_m, dv_m, 0.0) for c in range(3)], -1)
    ok_p, ok_m = ~breaks[axis_plus], ~breaks[axis_minus]
    ok_p, ok_m = ok_p & _inside(depth.shape, du_p, dv_p), ok_m & _inside(depth.shape, du_m, dv_m)
    g = jnp.where((ok_p & ok_m)[..., None], x_p - x_m,
                  jnp.where(ok_p[..., None], x_p - points, points - x_m))
    return g, ok_p | ok_m

  g_u, has_u = tangent((1, 0), (-1, 0))
  g_v, has_v = tangent((0, 1), (0, -1))
  normal = jnp.cross(g_u, g_v)
  norm_n = jnp.linalg.norm(normal, axis=-1)
  norm_x = jnp.linalg.norm(points, axis=-1)
  defined = ok & has_u & has_v & (norm_n > 0) & (norm_x > 0)
  cos = jnp.abs(jnp.sum(normal * points, -1)) / jnp.where(defined, norm_n * norm_x, 1.0)
  return jnp.where(defined, jnp.clip(cos, 0.0, 1.0), 1.0)


def _luminance_and_clipped(rgb):
  rgb = jnp.asarray(rgb)
  if rgb.dtype == jnp.uint8:
    rgb = rgb.astype(jnp.float32) / 255.0
  rgb = jnp.clip(jnp.where(jnp.isfinite(rgb), rgb.astype(jnp.float32), 0.0), 0.0, 1.0)
  lum = rgb @ jnp.array([0.299, 0.587, 0.114], jnp.float32)
  top = jnp.max(rgb, axis=-1)
  clipped = ((top >= CLIP_HIGH) | (top <= CLIP_LOW)).astype(jnp.float32)
  return lum, clipped


def _sharpness(lum):
  padded = jnp.pad(lum, 1, mode="edge")
  lap = (padded[1:-1, 2:] + padded[1:-1, :-2] + padded[2:, 1:-1] + padded[:-2, 1:-1]
         - 4.0 * lum)
  return jnp.sqrt(_window_mean(lap * lap))


def pixel_context(depth: jax.Array, probs: jax.Array, camera: camera_lib.Camera,
                  names: Sequence[str], rgb: Optional[jax.Array] = None) -> jax.Array:
  """The context features `names` of every pixel of one frame (docs/equations.md §2.5).

  Pure and jittable; `names` is static. Holes (depth 0, negative, non-finite) and non-finite
  probabilities or colours give finite values.

  Args:
    depth: `(H, W)` float z-depth in metres.
    probs: `(H, W, K)` float class probabilities (their argmax is the predicted label image).
    camera: pinhole intrinsics.
    names: the features, a sub-sequence of `FEATURES` in any order (F of them).
    rgb: `(H, W, 3)` uint8 or float in [0, 1] colour image; needed for `IMAGE_FEATURES`.

  Returns:
    `(H, W, F) float32`, feature f in channel f.

  Raises:
    ValueError: unknown or repeated names, or an image feature without `rgb`.
  """
  names = check_names(names)
  if needs_rgb(names) and rgb is None:
    raise ValueError(f"context features {[n for n in names if n in IMAGE_FEATURES]} read the "
                     "colour image: pass Frame(..., rgb=...)")
  depth = jnp.asarray(depth, jnp.float32)
  ok = jnp.isfinite(depth) & (depth > 0)
  z = jnp.where(ok, depth, 0.0)
  out = {}
  breaks = None
  if {"incidence", "depth_edge"} & set(names):
    breaks = {d: _discontinuity(z, ok, *d) for d in _NEIGHBOURS}
  if "depth" in names:
    out["depth"] = z
  if "incidence" in names:
    out["incidence"] = _incidence(camera_lib.backproject(z, camera), z, ok, breaks)
  if "depth_edge" in names:
    edges = breaks[(1, 0)] | breaks[(-1, 0)] | breaks[(0, 1)] | breaks[(0, -1)]
    out["depth_edge"] = _edge_distance(edges)
  if "label_edge" in names:
    p = jnp.asarray(probs, jnp.float32)
    label = jnp.argmax(jnp.where(jnp.isfinite(p), jnp.maximum(p, 0.0), 1.0 / p.shape[-1]), -1)
    edges = jnp.zeros(label.shape, bool)
    for du, dv in _NEIGHBOURS:
      edges = edges | (_inside(label.shape, du, dv) & (label != _shift(label, du, dv, -1)))
    out["label_edge"] = _edge_distance(edges)
  if "radius" in names:
    h, w = z.shape
    ru = (jnp.arange(w, dtype=jnp.float32)[None, :] - camera.cx) / camera.fx
    rv = (jnp.arange(h, dtype=jnp.float32)[:, None] - camera.cy) / camera.fy
    corners_u = (jnp.array([0.0, w - 1.0]) - camera.cx) / camera.fx
    corners_v = (jnp.array([0.0, h - 1.0]) - camera.cy) / camera.fy
    r_max = jnp.sqrt(jnp.max(corners_u**2)[None] + jnp.max(corners_v**2)[None])[0]
    out["radius"] = jnp.sqrt(ru * ru + rv * rv) / jnp.maximum(r_max, 1e-12)
  if needs_rgb(names):
    lum, clipped = _luminance_and_clipped(rgb)
    if "sharpness" in names:
      out["sharpness"] = _sharpness(lum)
    if "luminance" in names:
      out["luminance"] = _window_mean(lum)
    if "clipped" in names:
      out["clipped"] = _window_mean(clipped)
  shape = z.shape
  return jnp.stack([jnp.broadcast_to(out[n], shape).astype(jnp.float32) for n in names], -1)


pixel_context_jit = jax.jit(pixel_context, static_argnames=("names",))
