"""A slow, obvious NumPy version of the geometry layer's integration (docs/equations.md §8), for
tests: a dict from voxel index to (sdf, weight), written without any of the engine's code.
"""

import math

import numpy as np


class ReferenceTSDF:
  """Projective TSDF in blocks, one Python dict entry per voxel."""

  def __init__(self, *, voxel_size=0.05, truncation_voxels=4.0, block_size=8,
               weighting="constant", max_weight=100.0, max_depth=math.inf, block_stride=4):
    self.voxel_size = np.float32(voxel_size)
    self.tau = np.float32(voxel_size) * np.float32(truncation_voxels)
    self.truncation_voxels = truncation_voxels
    self.block_size = block_size
    self.weighting = weighting
    self.max_weight = max_weight
    self.max_depth = max_depth
    self.block_stride = block_stride   # blocks from every stride-th pixel and row (§8.2)
    self.blocks = set()
    self.voxels = {}   # (i, j, k) → [sdf, weight]

  def _blocks_of_frame(self, depth, T, cam):
    h, w = depth.shape
    ok = np.isfinite(depth) & (depth > 0) & (depth <= self.max_depth)
    samples = max(2, int(math.ceil(2 * self.truncation_voxels / (0.5 * self.block_size))) + 1)
    edge = np.float32(self.voxel_size * self.block_size)
    blocks = set()
    for v in range(0, h, self.block_stride):
      for u in range(0, w, self.block_stride):
        if not ok[v, u]:
          continue
        for s in range(samples):
          z = np.float32(depth[v, u] + self.tau * (2.0 * s / (samples - 1) - 1.0))
          if z <= 1e-4:
            continue
          p_cam = np.array([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z])
          p = T[:3, :3] @ p_cam + T[:3, 3]
          blocks.add(tuple(np.floor(p / edge).astype(int)))
    return blocks

  def integrate(self, depth, T, cam):
    depth = np.asarray(depth, np.float64)
    T = np.asarray(T, np.float64)
    h, w = depth.shape
    new_blocks = self._blocks_of_frame(depth, T, cam)
    self.blocks |= new_blocks
    b = self.block_size
    R, t = T[:3, :3], T[:3, 3]
    for block in new_blocks:
      for k in range(b):
        for j in range(b):
          for i in range(b):
            index = (block[0] * b + i, block[1] * b + j, block[2] * b + k)
            centre = (np.array(index) + 0.5) * float(self.voxel_size)
            x, y, z = R.T @ (centre - t)
            if z <= 1e-4:
              continue
            u = math.floor(cam.fx * x / z + cam.cx + 0.5)
            v = math.floor(cam.fy * y / z + cam.cy + 0.5)
            if not (0 <= u < w and 0 <= v < h):
              continue
            d = depth[v, u]
            if not (np.isfinite(d) and 0 < d <= self.max_depth):
              continue
            distance = (d - z) * math.sqrt(x * x + y * y + z * z) / z
            if distance < -self.tau:
              continue
            s = min(distance, self.tau)
            wt = 1.0 if self.weighting == "constant" else 1.0 / (d * d)
            sdf, weight = self.voxels.get(index, (0.0, 0.0))
            total = weight + wt
            self.voxels[index] = ((weight * sdf + wt * s) / total, min(total, self.max_weight))
