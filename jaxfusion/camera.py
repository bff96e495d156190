"""Pinhole camera, back-projection of depth images, and world points → integer voxel keys.

Conventions: the camera frame is OpenCV's (x right, y down, z forward); depth is z-depth; pixel
(u, v) is column u, row v with pixel centres at integer coordinates. Poses are camera-to-world
(`T_world_cam`). Shape legend: H×W pixels, N = H·W points.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

# Voxel coordinates are int32; points whose key would leave ±KEY_LIMIT are treated as invalid
# rather than wrapped around. At 0.1 m voxels this is ±107 000 km, far past the required ±1 km.
KEY_LIMIT = 2**30


class _Intrinsics(NamedTuple):
  fx: float
  fy: float
  cx: float
  cy: float


def _concrete_values(x):
  """`x` as a float64 NumPy array when it is a concrete number or numeric array, else None
  (tracers, and non-numeric placeholders such as a `vmap` axis spec's None)."""
  if isinstance(x, jax.core.Tracer) or isinstance(x, (bool, np.bool_)):
    return None
  if isinstance(x, (int, float, np.number, np.ndarray, jax.Array)):
    try:
      return np.asarray(x, np.float64)
    except (TypeError, ValueError):
      return None
  return None


class Camera(_Intrinsics):
  """Pinhole intrinsics in pixels. A pytree: every field is a (traceable) scalar.

  Built directly, a Camera checks its concrete values: `fx` and `fy` (focal lengths in pixels)
  must be finite and positive, `cx` and `cy` finite (ValueError otherwise). Tracers are not
  checked, and neither are the Cameras that JAX rebuilds from leaves (`jax.tree.map`, gradients,
  `vmap` outputs), which may legitimately hold other values.
  """
  __slots__ = ()

  def __new__(cls, fx, fy, cx, cy):
    for name, value in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)):
      v = _concrete_values(value)
      if v is None:
        continue
      if not np.all(np.isfinite(v)):
        raise ValueError(f"camera.{name} must be finite; got {value}")
      if name in ("fx", "fy") and not np.all(v > 0):
        raise ValueError(f"camera.{name} (focal length in pixels) must be positive; got {value}")
    return super().__new__(cls, fx, fy, cx, cy)

  @classmethod
  def from_matrix(cls, K) -> "Camera":
    """Builds a Camera from a `(3, 3)` (or larger, e.g. ScanNet's 4×4) intrinsics matrix."""
    K = np.asarray(K, dtype=np.float64)
    if K.ndim != 2 or K.shape[0] < 3 or K.shape[1] < 3:
      raise ValueError(f"intrinsics matrix must be at least 3x3; got shape {K.shape}")
    return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))

  def matrix(self) -> np.ndarray:
    """The `(3, 3) float64` intrinsics matrix."""
    return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


jax.tree_util.register_pytree_with_keys(
    Camera,
    lambda c: (tuple((jax.tree_util.GetAttrKey(k), v) for k, v in zip(Camera._fields, c)), None),
    lambda _, leaves: tuple.__new__(Camera, leaves),     # JAX's rebuilds are not checked
    flatten_func=lambda c: (tuple(c), None))


def backproject(depth: jax.Array, camera: Camera) -> jax.Array:
  """Back-projects a depth image into camera-frame points.

  Args:
    depth: `(H, W)` float z-depth in metres.
    camera: intrinsics.

  Returns:
    `(H, W, 3) float32` points `(D·(u−cx)/fx, D·(v−cy)/fy, D)`.
  """
  depth = jnp.asarray(depth, jnp.float32)
  x, y = _pixel_xy(depth, camera)
  return jnp.stack([x, y, depth], axis=-1)


def _pixel_xy(depth: jax.Array, camera: Camera) -> tuple[jax.Array, jax.Array]:
  """Camera-frame `x = D·(u−cx)/fx` and `y = D·(v−cy)/fy` of every pixel, each `(H, W)`."""
  height, width = depth.shape
  u = jnp.arange(width, dtype=jnp.float32)[None, :]
  v = jnp.arange(height, dtype=jnp.float32)[:, None]
  return depth * ((u - camera.cx) / camera.fx), depth * ((v - camera.cy) / camera.fy)


def transform_points(T_a_b: jax.Array, p_b: jax.Array) -> jax.Array:
  """Applies the rigid transform `T_a_b (4, 4)` to points `p_b (..., 3)` → `p_a (..., 3)`."""
  T_a_b = jnp.asarray(T_a_b, jnp.float32)
  t = T_a_b[:3, 3].reshape((1,) * (p_b.ndim - 1) + (3,))
  return p_b @ T_a_b[:3, :3].T + t


def voxel_keys(p_world: jax.Array, voxel_size: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Integer voxel coordinates `floor(p / voxel_size)` of world points.

  Args:
    p_world: `(N, 3)` float world points (may hold NaN/inf for invalid pixels).
    voxel_size: scalar voxel edge in metres.

  Returns:
    `(keys, in_range)`: `(N, 3) int32` keys (0 where out of range) and `(N,) bool`, False for
    non-finite points and keys outside ±KEY_LIMIT (never wrapped around).
  """
  scaled = jnp.floor(p_world / voxel_size)
  in_range = jnp.all(jnp.isfinite(scaled) & (jnp.abs(scaled) < KEY_LIMIT), axis=-1)
  keys = jnp.where(in_range[:, None], scaled, 0.0).astype(jnp.int32)
  return keys, in_range


def depth_to_voxel_keys(depth: jax.Array, T_world_cam: jax.Array, camera: Camera,
                        voxel_size: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Voxel keys of every pixel of a depth image, in one elementwise pass.

  The same arithmetic as `voxel_keys(transform_points(T, backproject(depth, camera)), size)`,
  written per coordinate so that XLA fuses it into one loop over the pixels instead of
  materialising `(N, 3)` points and calling a `(N, 3) × (3, 3)` matrix product.

  Args:
    depth: `(H, W)` float z-depth in metres.
    T_world_cam: `(4, 4)` float camera-to-world pose.
    camera: intrinsics.
    voxel_size: scalar voxel edge in metres.

  Returns:
    `(keys, in_range)`: `(H·W, 3) int32` keys (0 where out of range) and `(H·W,) bool`, False
    for non-finite points and keys outside ±KEY_LIMIT, as `voxel_keys`.
  """
  depth = jnp.asarray(depth, jnp.float32)
  T = jnp.asarray(T_world_cam, jnp.float32)
  height, width = depth.shape
  x, y = _pixel_xy(depth, camera)
  scaled = [jnp.floor((x * T[i, 0] + y * T[i, 1] + depth * T[i, 2] + T[i, 3]) / voxel_size)
            for i in range(3)]
  in_range = jnp.ones_like(depth, dtype=bool)
  for s in scaled:
    in_range = in_range & jnp.isfinite(s) & (jnp.abs(s) < KEY_LIMIT)
  keys = jnp.stack([jnp.where(in_range, s, 0.0).astype(jnp.int32) for s in scaled], axis=-1)
  return keys.reshape(height * width, 3), in_range.reshape(height * width)
