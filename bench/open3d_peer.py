"""Open3D's CPU TSDF integration of the same frames: an external yardstick of what per-frame
integration costs in a mature C++ library. Optional: Open3D is never a dependency of jaxfusion.

It is not the same computation (a TSDF with a weight per voxel, no classes), so the ratio says
how our per-frame cost compares with a well-engineered voxel-hashing integrator, nothing more.
Measured with `open3d.t.geometry.VoxelBlockGrid` (blocks of 8³ voxels of `voxel_size`, attributes
tsdf and weight; `compute_unique_block_coordinates` + `integrate` per frame, as Open3D's own
integration example does).
"""

import sys
import time
import types

import numpy as np


def _import_open3d():
  """Imports open3d, or returns None. Open3D's package imports its Plotly/Dash viewers at import
  time; when those optional viewers are not installed, empty stand-ins let the core import (the
  viewers are never used here)."""
  try:
    import open3d  # pylint: disable=import-outside-toplevel
    return open3d
  except ImportError:
    pass
  stand_ins = {}
  for name in ("plotly", "plotly.graph_objects", "dash"):
    if name not in sys.modules:
      module = types.ModuleType(name)
      module.html = module.dcc = module.Dash = None      # the names open3d's viewers look up
      stand_ins[name] = module
  sys.modules.update(stand_ins)
  try:
    import open3d  # pylint: disable=import-outside-toplevel
    return open3d
  except ImportError:
    return None
  finally:
    for name in stand_ins:
      sys.modules.pop(name, None)


def measure(frames, *, voxel_size: float = 0.1, repeats: int = 5, trunc_voxels: float = 4.0,
            block_resolution: int = 8) -> dict:
  """Median per-frame TSDF integration time of `frames` (a `bench.scene.BenchFrames`).

  Returns:
    dict with `ms_per_frame`, or `status` "not installed" when open3d cannot be imported.
  """
  o3d = _import_open3d()
  if o3d is None:
    return {"status": "not installed"}
  o3c = o3d.core
  device = o3c.Device("CPU:0")
  num_frames, height, width = frames.depth.shape
  cam = frames.camera
  intrinsic = o3c.Tensor(np.array([[cam.fx, 0, cam.cx], [0, cam.fy, cam.cy], [0, 0, 1]],
                                  np.float64))
  depths = [o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(d, np.float32)))
            for d in frames.depth]
  extrinsics = [o3c.Tensor(np.linalg.inv(T.astype(np.float64))) for T in frames.poses]
  grid = o3d.t.geometry.VoxelBlockGrid(
      attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
      attr_channels=((1,), (1,)), voxel_size=voxel_size, block_resolution=block_resolution,
      block_count=50000, device=device)
  t = [0]

  def step():
    i = t[0] % num_frames
    t[0] += 1
    coords = grid.compute_unique_block_coordinates(
        depths[i], intrinsic, extrinsics[i], depth_scale=1.0, depth_max=6.5,
        trunc_voxel_multiplier=trunc_voxels)
    grid.integrate(coords, depths[i], intrinsic, extrinsics[i], depth_scale=1.0,
                   depth_max=6.5, trunc_voxel_multiplier=trunc_voxels)

  step()
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    step()
    times.append(time.perf_counter() - t0)
  return {"version": o3d.__version__, "method": "t.geometry.VoxelBlockGrid.integrate",
          "voxel_size": voxel_size,
          "detail": f"blocks {block_resolution}³, trunc {trunc_voxels} voxels, {height}×{width}",
          "ms_per_frame": 1e3 * float(np.median(times))}
