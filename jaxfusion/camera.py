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


class Camera(NamedTuple):
  """Pinhole intrinsics in pixels. A pytree: every field is a (traceable) scalar."""
  fx: float
  fy: float
  cx: float
  cy: float

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


def backproject(depth: jax.Array, camera: Camera) -> jax.Array:
  """Back-projects a depth image into camera-frame points.

  Args:
    depth: `(H, W)` float z-depth in metres.
    camera: intrinsics.

  Returns:
    `(H, W, 3) float32` points `(D·(u−cx)/fx, D·(v−cy)/fy, D)`.
  """
  depth = jnp.asarray(depth, jnp.float32)
  height, width = depth.shape
  u = jnp.arange(width, dtype=jnp.float32)[None, :]
  v = jnp.arange(height, dtype=jnp.float32)[:, None]
  x = depth * ((u - camera.cx) / camera.fx)
  y = depth * ((v - camera.cy) / camera.fy)
  return jnp.stack([x, y, depth], axis=-1)


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
