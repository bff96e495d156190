"""Realistic indoor frames for the benchmarks, made without the dataset package.

A box-shaped room (6 × 5 × 3 m) with a few boxes standing in it, ray cast in NumPy from a random
pose inside the room. The room is modelled with walls and box faces on whole decimetres and placed
in the world at a sub-voxel offset (`OFF_GRID`), so that, as in a real room, no surface lies on a
face of the 0.1 m voxel grid (`aligned=True` keeps them on the faces: with depth noise each
such surface splits across two voxel layers, a stress case), so that depths lie between about 0.5 and 6 m and a frame touches the number
of voxels a real indoor frame does. The class probabilities are a smooth, peaked Dirichlet-like
field (one dominant class per object, a few pixels ambiguous) and the variances a plausible
MC-dropout spread, so every rule does its full work.

Shape legend: H×W pixels, K classes, T frames.
"""

from typing import NamedTuple

import numpy as np

import jaxfusion as jf

ROOM_MIN = np.array([-3.0, -2.5, 0.0])
ROOM_MAX = np.array([3.0, 2.5, 3.0])
# Where the room's origin sits in the world (metres): 0.37, 0.39 and 0.43 of a 0.1 m voxel off the
# grid along x, y and z, so walls, floor and box faces lie inside voxels, not on their faces.
OFF_GRID = np.array([0.037, -0.061, 0.043])
# (min corner, max corner, class) of the furniture boxes.
BOXES = (
    ((-2.5, -2.0, 0.0), (-1.2, -1.0, 0.8), 1),
    ((0.5, 1.0, 0.0), (2.0, 2.2, 0.75), 2),
    ((1.5, -2.3, 0.0), (2.8, -1.5, 1.9), 3),
    ((-0.6, -0.3, 0.0), (0.3, 0.5, 0.45), 4),
)


class BenchFrames(NamedTuple):
  """A stack of frames and the camera that took them (NumPy float32)."""
  depth: np.ndarray     # [T, H, W]
  poses: np.ndarray     # [T, 4, 4] camera-to-world
  probs: np.ndarray     # [T, H, W, K]
  var: np.ndarray       # [T, H, W, K]
  camera: jf.Camera

  def frame(self, t: int) -> jf.Frame:
    return jf.Frame(self.depth[t], self.poses[t], self.probs[t], self.var[t])

  def stacked(self) -> jf.Frame:
    return jf.Frame(self.depth, self.poses, self.probs, self.var)


def camera_for(height: int, width: int) -> jf.Camera:
  """A Kinect-like pinhole camera (about 58° horizontal field of view)."""
  f = 525.0 * width / 640.0
  return jf.Camera(f, f, (width - 1) / 2.0, (height - 1) / 2.0)


def _look_at(eye, target):
  """Camera-to-world pose (OpenCV axes) looking from `eye` at `target`, world z up."""
  z = target - eye
  z = z / np.linalg.norm(z)
  x = np.cross(z, np.array([0.0, 0.0, 1.0]))
  x = x / np.linalg.norm(x)
  y = np.cross(z, x)
  T = np.eye(4)
  T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, eye
  return T


def _ray_cast(T, camera, height, width):
  """Depth `(H, W)` and class id `(H, W)` of the first surface each pixel's ray hits."""
  v, u = np.mgrid[0:height, 0:width].astype(np.float64)
  d_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy,
                    np.ones_like(u)], -1)
  d = d_cam @ T[:3, :3].T                         # world direction per unit z-depth
  o = T[:3, 3]
  with np.errstate(divide="ignore", invalid="ignore"):
    inv = 1.0 / d
    # Inside the room: the ray leaves through the nearest wall.
    t_far = np.maximum((ROOM_MIN - o) * inv, (ROOM_MAX - o) * inv)
    depth = np.min(t_far, axis=-1)
    wall = np.argmin(t_far, axis=-1)
    label = np.where(wall == 2, 0, 5 + wall)      # floor/ceiling 0, walls 5/6
    for lo, hi, cls in BOXES:
      t1 = (np.array(lo) - o) * inv
      t2 = (np.array(hi) - o) * inv
      t_in = np.max(np.minimum(t1, t2), axis=-1)
      t_out = np.min(np.maximum(t1, t2), axis=-1)
      hit = (t_in <= t_out) & (t_in > 0) & (t_in < depth)
      depth = np.where(hit, t_in, depth)
      label = np.where(hit, cls, label)
  return depth, label


def make_frames(num_frames: int, *, height: int = 480, width: int = 640, num_classes: int = 13,
                seed: int = 0, hole_fraction: float = 0.03, aligned: bool = False
                ) -> BenchFrames:
  """Renders `num_frames` indoor frames from random poses in the room.

  Args:
    num_frames: T.
    height: H.
    width: W.
    num_classes: K ≥ 7.
    seed: random seed (poses, noise, probabilities).
    hole_fraction: fraction of pixels with no depth (0), as real sensors have.
    aligned: put the room's surfaces on voxel faces (no `OFF_GRID` offset), a stress case.

  Returns:
    BenchFrames with depths clipped to [0.5, 6] m (farther or nearer pixels are holes).
  """
  rng = np.random.default_rng(seed)
  camera = camera_for(height, width)
  depths, poses, probs, variances = [], [], [], []
  for _ in range(num_frames):
    eye = rng.uniform([-2.0, -1.5, 1.0], [2.0, 1.5, 1.8])
    target = rng.uniform([-3.0, -2.5, 0.2], [3.0, 2.5, 1.5])
    while np.linalg.norm(target - eye) < 1.0:
      target = rng.uniform([-3.0, -2.5, 0.2], [3.0, 2.5, 1.5])
    T = _look_at(eye, target)
    depth, label = _ray_cast(T, camera, height, width)
    depth = depth * (1.0 + rng.normal(0.0, 0.003, depth.shape))   # sensor noise
    depth[(depth < 0.5) | (depth > 6.0) | (rng.random(depth.shape) < hole_fraction)] = 0.0
    label = label % num_classes
    logits = rng.normal(0.0, 1.0, (height, width, num_classes))
    logits[np.arange(height)[:, None], np.arange(width)[None, :], label] += 3.0
    p = np.exp(logits - logits.max(-1, keepdims=True))
    p /= p.sum(-1, keepdims=True)
    var = p * (1.0 - p) * rng.uniform(0.01, 0.2, (height, width, 1))
    depths.append(depth.astype(np.float32))
    if not aligned:
      T = T.copy()
      T[:3, 3] += OFF_GRID                        # room frame → world frame
    poses.append(T.astype(np.float32))
    probs.append(p.astype(np.float32))
    variances.append(var.astype(np.float32))
  return BenchFrames(np.stack(depths), np.stack(poses), np.stack(probs), np.stack(variances),
                     camera)
