"""Input checks for the public entry points, raising ValueError/TypeError with clear messages.

Shape and dtype checks run at trace time, so they also guard calls made under `jit`, `vmap` or
`grad`. Value checks (finite rigid pose, positive intrinsics, non-negative probabilities) need
concrete data and run only when the inputs are not tracers.

The sign checks of probabilities and variances read data, so their cost is chosen per entry
point: `fuse_frame` (called once per frame) checks a fixed strided sample of at most
`SAMPLED_PIXELS` pixels — microseconds at any image size, and enough to catch the real mistakes
(log-probabilities, logits, signed or centred arrays) with a clear error — while the sequence
and batch entry points check every value once per call. An isolated negative entry that the
sample misses is harmless: the engine reads probabilities as `max(p, 0)` and clips variances to
[0, 0.25].
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion.camera import Camera
from jaxfusion.context import IMAGE_FEATURES as _IMAGE_FEATURES
from jaxfusion.rules import base as rules_base

_RIGID_TOL = 1e-3
_VAR_TOL = -1e-6
# Pixels whose class values the sampled sign check of `check_frame(..., sample=True)` reads.
SAMPLED_PIXELS = 4096


def _is_concrete(*xs) -> bool:
  return all(not isinstance(x, jax.core.Tracer) for x in xs)


def _dtype(x):
  return np.asarray(x).dtype if not hasattr(x, "dtype") else x.dtype


def _check_float(x, name, hint=""):
  dtype = _dtype(x)
  if not jnp.issubdtype(dtype, jnp.floating):
    raise TypeError(f"{name} must be a float array; got dtype {dtype}{hint}")


def check_camera(camera) -> None:
  if not isinstance(camera, Camera):
    raise TypeError(f"camera must be a jaxfusion.Camera(fx, fy, cx, cy); got "
                    f"{type(camera).__name__}")
  for name in ("fx", "fy", "cx", "cy"):
    value = getattr(camera, name)
    if np.ndim(value) != 0:
      raise ValueError(f"camera.{name} must be a scalar; got shape {np.shape(value)}")
    if _is_concrete(value):
      v = float(np.asarray(value))
      if not math.isfinite(v):
        raise ValueError(f"camera.{name} must be finite; got {v}")
      if name in ("fx", "fy") and v <= 0:
        raise ValueError(f"camera.{name} (focal length in pixels) must be positive; got {v}")


def check_pose_values(T: np.ndarray, name: str = "T_world_cam") -> None:
  """Raises unless every `(..., 4, 4)` pose is finite and rigid (rotation + translation)."""
  T = np.asarray(T, np.float64)
  if not np.all(np.isfinite(T)):
    raise ValueError(f"{name} must be finite; got a pose with NaN/inf entries")
  R = T[..., :3, :3]
  should_be_identity = np.einsum("...ji,...jk->...ik", R, R)
  if np.max(np.abs(should_be_identity - np.eye(3)), initial=0.0) > _RIGID_TOL:
    raise ValueError(f"{name} is not rigid: its 3x3 rotation block is not orthonormal")
  if np.any(np.linalg.det(R) <= 0):
    raise ValueError(f"{name} is not rigid: its rotation block has a negative determinant")
  if np.max(np.abs(T[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])), initial=0.0) > _RIGID_TOL:
    raise ValueError(f"{name} must have last row [0, 0, 0, 1]")


@functools.partial(jax.jit, static_argnums=1)
def _strided_mins(arrays, strides):
  # NaN-ignoring minima: a NaN elsewhere in the array must not hide a negative value (NaN < 0 is
  # False); non-finite pixels are skipped by the engine, negative ones are refused. On XLA-CPU the
  # NaN guard makes this reduction ~7x slower than a plain one, so it only runs on arrays that
  # hold a NaN (`_strided_min_and_sum`).
  return jnp.stack([jnp.nanmin(x.reshape(-1, x.shape[-1])[::s]) for x, s in zip(arrays, strides)])


@functools.partial(jax.jit, static_argnums=1)
def _strided_min_and_sum(arrays, strides):
  # The plain minimum is exact for an array without NaN, and the sum tells whether there is one:
  # it is NaN if and only if an entry is NaN (or +inf and -inf are both present, which only sends
  # the array to the guarded path).
  flat = [x.reshape(-1, x.shape[-1])[::s] for x, s in zip(arrays, strides)]
  return jnp.stack([jnp.min(f) for f in flat]), jnp.stack([jnp.sum(f) for f in flat])


def _min_values(arrays, sample: bool) -> list:
  """Smallest non-NaN entry of each `(..., K)` array (NaN if all are): of all of it, or
  (`sample`) of every s-th pixel, at most `SAMPLED_PIXELS` pixels, the first one included (a
  view for NumPy arrays, one small jitted gather for all device arrays together)."""
  out, on_device = [], []
  for i, x in enumerate(arrays):
    pixels = math.prod(np.shape(x)[:-1])
    if pixels == 0 or np.shape(x)[-1] == 0:
      out.append(math.inf)
      continue
    stride = max(1, -(-pixels // SAMPLED_PIXELS)) if sample else 1
    if isinstance(x, jax.Array):
      out.append(None)
      on_device.append((i, x, stride))
      continue
    x = np.asarray(x)
    out.append(float(np.fmin.reduce(x.reshape(-1, x.shape[-1])[::stride], axis=None)))
  if on_device:
    mins, sums = _strided_min_and_sum(tuple(x for _, x, _ in on_device),
                                      tuple(s for _, _, s in on_device))
    with_nan = []
    for (i, x, stride), m, total in zip(on_device, np.asarray(mins), np.asarray(sums)):
      if np.isnan(total):
        with_nan.append((i, x, stride))
      else:
        out[i] = float(m)
    if with_nan:
      guarded = np.asarray(_strided_mins(tuple(x for _, x, _ in with_nan),
                                         tuple(s for _, _, s in with_nan)))
      for (i, _, _), m in zip(with_nan, guarded):
        out[i] = float(m)
  return out


def check_frame(frame, *, num_classes: int, requires_var: bool, rule_name: str,
                batch_dims: int = 0, sample: bool = False, context: tuple = ()) -> None:
  """Checks one Frame (`batch_dims=0`) or a stack of frames (`batch_dims=1`).

  Shapes, dtypes and poses are always checked in full; with `sample=True` the signs of `probs`
  and `var` are checked on a strided sample of pixels (see the module docstring), else on all.
  """
  lead = "(T, " if batch_dims else "("
  depth, T, probs, var = frame.depth, frame.T_world_cam, frame.probs, frame.var
  if np.ndim(depth) != 2 + batch_dims:
    raise ValueError(f"depth must have shape {lead}H, W); got shape {np.shape(depth)}")
  _check_float(depth, "depth", " (convert integer depth images to metres, e.g. mm / 1000)")
  if np.shape(T)[batch_dims:] != (4, 4) or np.ndim(T) != 2 + batch_dims:
    raise ValueError(f"T_world_cam must have shape {lead}4, 4); got shape {np.shape(T)}")
  _check_float(T, "T_world_cam")
  if np.ndim(probs) != 3 + batch_dims:
    raise ValueError(f"probs must have shape {lead}H, W, K); got shape {np.shape(probs)}")
  _check_float(probs, "probs")
  if np.shape(probs)[:-1] != np.shape(depth):
    raise ValueError(f"probs {np.shape(probs)} and depth {np.shape(depth)} must cover the same "
                     "pixels")
  if np.shape(probs)[-1] != num_classes:
    raise ValueError(f"K mismatch: the map has {num_classes} classes but probs has "
                     f"{np.shape(probs)[-1]}")
  if var is not None:
    if np.shape(var) != np.shape(probs):
      raise ValueError(f"var must have the shape of probs {np.shape(probs)}; got "
                       f"{np.shape(var)}")
    _check_float(var, "var")
  elif requires_var:
    raise ValueError(f"rule {rule_name!r} weights observations by their epistemic variance: "
                     "pass Frame(..., var=...) (e.g. from jaxfusion.mc_moments(samples))")
  rgb = getattr(frame, "rgb", None)
  if rgb is not None:
    if np.shape(rgb) != np.shape(depth) + (3,):
      raise ValueError(f"rgb must have shape {lead}H, W, 3) with the depth's (H, W) "
                       f"{np.shape(depth)[batch_dims:]}; got shape {np.shape(rgb)}")
    if _dtype(rgb) != np.uint8 and not jnp.issubdtype(_dtype(rgb), jnp.floating):
      raise TypeError(f"rgb must be uint8 or float in [0, 1]; got dtype {_dtype(rgb)}")
  elif any(name in _IMAGE_FEATURES for name in context):
    raise ValueError(f"rule {rule_name!r} reads image context features "
                     f"{[n for n in context if n in _IMAGE_FEATURES]}: pass "
                     "Frame(..., rgb=...), the colour image registered to the depth")
  if batch_dims == 0 and np.shape(depth)[0] * np.shape(depth)[1] == 0:
    raise ValueError(f"depth must have at least one pixel; got shape {np.shape(depth)}")
  if _is_concrete(T):
    check_pose_values(T)
  checked = [x for x in (probs, var) if x is not None and _is_concrete(x)]
  mins = dict(zip(map(id, checked), _min_values(checked, sample)))
  if id(probs) in mins and mins[id(probs)] < 0:
    raise ValueError("probs must be non-negative class probabilities (softmax outputs, not "
                     "logits or log-probabilities); got negative values")
  if var is not None and id(var) in mins and mins[id(var)] < _VAR_TOL:
    raise ValueError("var must be non-negative; got negative variances")


def check_rule_matches_map(state, rule) -> None:
  if not isinstance(rule, rules_base.FusionRule):
    raise TypeError(f"rule must be a jaxfusion.rules.FusionRule; got {type(rule).__name__}")
  if rule.name != state.rule_name:
    raise ValueError(f"this map was made for rule {state.rule_name!r} but is being fused with "
                     f"{rule.name!r}; make the map with init_map(..., rule=rule)")
