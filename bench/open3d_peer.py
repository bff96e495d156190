"""Open3D's CPU TSDF integration and meshing of the same frames: an external yardstick of what
per-frame integration and marching cubes cost in a mature C++ library. Optional: Open3D is never
a dependency of jaxfusion (`pip install -e .[bench]` installs it; Debian also needs libusb-1.0-0).

`measure` times integration only, against the semantic fusion (not the same computation: a TSDF
with a weight per voxel, no classes), so its ratio says how our per-frame cost compares with a
well-engineered voxel-hashing integrator, nothing more. `tsdf_peer` is the like-for-like peer of
jaxfusion's TSDF layer: integration, `extract_triangle_mesh`, the mesh, memory.
Both use `open3d.t.geometry.VoxelBlockGrid` (blocks of `block_resolution`³ voxels of
`voxel_size`, attributes tsdf and weight, float32; `compute_unique_block_coordinates` +
`integrate` per frame, as Open3D's own integration example does).

What Open3D computes (read in Open3D's source, isl-org/Open3D at 22a6a307b, 2026-08, 0.19+dev;
the TSDF kernels are unchanged since 2022 but for a TBB port: `cpp/open3d/t/geometry/
VoxelBlockGrid.cpp`, `cpp/open3d/t/geometry/kernel/VoxelBlockGridImpl.h` (IntegrateCPU,
ExtractTriangleMeshCPU), `kernel/VoxelBlockGridCPU.cpp` (DepthTouchCPU),
`kernel/GeometryIndexer.h` (TransformIndexer, InBoundary), `core/hashmap/HashMap.cpp`,
`core/hashmap/HashBackendBuffer.cpp`, `core/hashmap/CPU/TBBHashBackend.h`,
`cpp/pybind/t/geometry/voxel_block_grid.cpp`):

* Grid. Voxel of integer index (x, y, z) (= block key · R + offset in block, R the block
  resolution) has its sample point at (x, y, z) · voxel_size in the world: integer multiples of
  the voxel size, no +½. Block key = floor(p / (R · voxel_size)).
* Which blocks (`compute_unique_block_coordinates`, DepthTouchCPU): every 4th pixel in both image
  axes with 0 < d < depth_max; along its ray, 4 points evenly spaced in z-depth from
  max(d − trunc, 0) to min(d + trunc, depth_max) (trunc = trunc_voxels · voxel_size); the blocks
  containing them. `integrate` activates these blocks (new blocks are not zeroed by the hash map;
  fresh pages from the OS are zero, see `_check_attributes`) and updates only them: other
  allocated blocks in view are left as they are.
* Which voxels, what sdf (IntegrateCPU): every voxel of those blocks; its point goes to camera
  coordinates (xc, yc, zc) and projects to (u, v) = (fx·xc/zc + cx, fy·yc/zc + cy); skipped unless
  0 ≤ u ≤ W − 1 and 0 ≤ v ≤ H − 1; the depth is read at pixel (int(u), int(v)), i.e. truncated
  (floor), not rounded to the nearest pixel centre. sdf = depth − zc: the difference of z-depths
  along the optical axis, not the distance along the ray. Skipped when depth ≤ 0, depth >
  depth_max, zc ≤ 0 or sdf < −trunc (voxels more than trunc behind the surface are never
  touched). Otherwise tsdf_new = min(sdf, trunc) / trunc ∈ [−1, 1] (stored normalised; free space
  in front is clipped to +1 and still counted).
* Weights: constant 1 per observation: tsdf ← (w · tsdf + tsdf_new) / (w + 1), w ← w + 1, no cap
  and no other weighting: the Python and C++ `integrate` take no weight argument (only
  depth_scale, depth_max, trunc_voxel_multiplier). Hence only `weighting="constant"`,
  `max_weight=None` are comparable here; anything else returns status "unsupported".
* Mesh (ExtractTriangleMeshCPU): marching cubes over every cube (x..x+1, y..y+1, z..z+1) of
  allocated voxels whose 8 corners all lie in allocated blocks (neighbour blocks via the hash
  map) and all have weight > weight_threshold (strictly; the Python default is 3.0); a corner is
  inside when tsdf < 0; a vertex per sign-changing edge at voxel_size · (x + t) with t =
  −tsdf_o / (tsdf_e − tsdf_o), shared between the cubes of that edge (an indexed mesh); triangle
  winding reversed from the table (`2 − vertex`); vertex normals from central differences of tsdf.
  Float32 vertices, int32 triangle indices; vertex and triangle order follow atomic counters, so
  they differ from run to run (the mesh does not).
* Memory: the hash map (CPU: a TBB concurrent_unordered_map from block key to buffer index) keeps
  buffers of `capacity` entries: keys (capacity × 3 int32), one value buffer per attribute
  (capacity × R³ × channels × dtype), and a heap of free buffer indices (capacity × uint32, not
  exposed to Python). The capacity doubles when an activation would exceed it (`Reserve`, which
  re-inserts every block). The TBB map's own nodes and buckets and the per-frame "frustum" hash map
  of `compute_unique_block_coordinates` are not exposed; `grid_rss_growth_bytes` measures them
  along with the rest.
"""

import multiprocessing
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


def _inputs(o3d, depth, poses, camera):
  """Open3D's intrinsic matrix, depth images and world-to-camera extrinsics of the frames."""
  o3c = o3d.core
  fx, fy, cx, cy = camera
  intrinsic = o3c.Tensor(np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]], np.float64))
  depths = [o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(d, np.float32))) for d in depth]
  extrinsics = [o3c.Tensor(np.linalg.inv(T.astype(np.float64))) for T in poses]
  return intrinsic, depths, extrinsics


def _camera(frames):
  cam = frames.camera
  return (float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy))


def _new_grid(o3d, voxel_size, block_resolution, block_count):
  o3c = o3d.core
  return o3d.t.geometry.VoxelBlockGrid(
      attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32),
      attr_channels=((1,), (1,)), voxel_size=voxel_size, block_resolution=block_resolution,
      block_count=block_count, device=o3c.Device("CPU:0"))


def measure(frames, *, voxel_size: float = 0.1, repeats: int = 5, trunc_voxels: float = 4.0,
            block_resolution: int = 8) -> dict:
  """Median per-frame TSDF integration time of `frames` (a `bench.scene.BenchFrames`).

  Returns:
    dict with `ms_per_frame`, or `status` "not installed" when open3d cannot be imported.
  """
  o3d = _import_open3d()
  if o3d is None:
    return {"status": "not installed"}
  num_frames, height, width = frames.depth.shape
  intrinsic, depths, extrinsics = _inputs(o3d, frames.depth, frames.poses, _camera(frames))
  grid = _new_grid(o3d, voxel_size, block_resolution, 50000)
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


def _integrate_all(o3d, grid, intrinsic, depths, extrinsics, depth_max, trunc_voxels):
  """Integrates every frame in order; seconds of block selection and of integration per frame."""
  touch, integrate = [], []
  for depth, extrinsic in zip(depths, extrinsics):
    t0 = time.perf_counter()
    coords = grid.compute_unique_block_coordinates(
        depth, intrinsic, extrinsic, depth_scale=1.0, depth_max=depth_max,
        trunc_voxel_multiplier=trunc_voxels)
    t1 = time.perf_counter()
    grid.integrate(coords, depth, intrinsic, extrinsic, depth_scale=1.0, depth_max=depth_max,
                   trunc_voxel_multiplier=trunc_voxels)
    t2 = time.perf_counter()
    touch.append(t1 - t0)
    integrate.append(t2 - t1)
  del o3d
  return touch, integrate


def _active_attributes(grid):
  """tsdf and weight of the allocated voxels, `(blocks · R³,)` float32 each."""
  active = grid.hashmap().active_buf_indices().numpy().astype(np.int64)
  tsdf = grid.attribute("tsdf").numpy()[active].reshape(-1)
  weight = grid.attribute("weight").numpy()[active].reshape(-1)
  return tsdf, weight


def _check_attributes(tsdf, weight, num_frames):
  """Whether every allocated voxel holds what constant-weight integration can hold: a weight
  that is a whole number of observations in [0, T] and a tsdf in [−1, 1] (0 when unobserved).
  New blocks are activated without zeroing (TBBHashBackend::Insert with no values), so this
  catches a block that started from reused, non-zero memory."""
  whole = np.all(weight == np.round(weight)) and np.all((weight >= 0) & (weight <= num_frames))
  bounded = np.all(np.abs(tsdf) <= 1.0) and np.all(tsdf[weight == 0] == 0.0)
  return bool(whole and bounded)


def _status_kb(field):
  with open("/proc/self/status", encoding="ascii") as f:
    for line in f:
      if line.startswith(field + ":"):
        return int(line.split()[1])
  raise KeyError(field)


def _mesh_memory_child(depth, poses, camera, voxel_size, block_resolution, block_count,
                       depth_max, trunc_voxels, weight_threshold):
  """Runs in a fresh process: integrates the frames, then resets the kernel's RSS high-water
  mark (`echo 5 > /proc/self/clear_refs`) and extracts the mesh once. Returns bytes."""
  import gc  # pylint: disable=import-outside-toplevel
  o3d = _import_open3d()
  intrinsic, depths, extrinsics = _inputs(o3d, depth, poses, camera)
  gc.collect()
  rss0 = _status_kb("VmRSS")
  grid = _new_grid(o3d, voxel_size, block_resolution, block_count)
  _integrate_all(o3d, grid, intrinsic, depths, extrinsics, depth_max, trunc_voxels)
  gc.collect()
  rss1 = _status_kb("VmRSS")
  try:
    with open("/proc/self/clear_refs", "w", encoding="ascii") as f:
      f.write("5")
    reset = True
  except OSError:
    reset = False
  rss2 = _status_kb("VmRSS")
  mesh = grid.extract_triangle_mesh(weight_threshold=weight_threshold)
  hwm = _status_kb("VmHWM")
  rss3 = _status_kb("VmRSS")
  num_triangles = int(mesh.triangle.indices.shape[0])
  return {"grid_rss_growth_bytes": 1024 * (rss1 - rss0),
          "mesh_peak_bytes": 1024 * (hwm - rss2),
          "mesh_retained_bytes": 1024 * (rss3 - rss2),
          "mesh_rss_before_bytes": 1024 * rss2,
          "hwm_reset": reset, "child_num_triangles": num_triangles}


def _mesh_memory(frames, **kwargs):
  context = multiprocessing.get_context("spawn")
  with context.Pool(1) as pool:
    return pool.apply(_mesh_memory_child,
                      (np.asarray(frames.depth), np.asarray(frames.poses), _camera(frames)),
                      kwargs)


def tsdf_peer(frames, *, voxel_size: float, trunc_voxels: float = 4.0, block_resolution: int = 8,
              weighting: str = "constant", max_weight=None, depth_max: float = 6.5,
              repeats: int = 5, weight_threshold: float = 0.0, block_count=None,
              memory: bool = True) -> dict:
  """Open3D's TSDF of `frames` (a `bench.scene.BenchFrames`): integration and mesh timings, the
  mesh, and memory. What Open3D computes is in the module docstring.

  Integration: a warm-up pass integrates the whole sequence into a new grid (Open3D's hash map
  starting at `block_count`, default 1024 blocks, and doubling as it fills); then `repeats`
  passes each integrate the whole sequence, in order, into a new grid whose capacity is the one the
  warm-up ended at (so no pass rehashes). Each frame's `compute_unique_block_coordinates` +
  `integrate` is timed; `integrate_ms_per_frame` is the median over all frames of all passes.
  Meshing: `extract_triangle_mesh(weight_threshold)` on the last pass's grid, once to warm up,
  then `repeats` times; `mesh_ms` is the median. A cube is meshed only when all 8 corners have
  weight > `weight_threshold` (Open3D's own default is 3.0, i.e. 4 observations; 0.0, the default
  here, meshes every observed cube).

  Memory: bytes of the hash map's buffers read from its tensors (keys, value buffers) and its
  heap (capacity × 4 B, from the source), per allocated voxel; and, when `memory`, measured in a
  fresh process (multiprocessing 'spawn'): RSS growth of building and integrating the grid, and
  the peak of meshing = VmHWM after `extract_triangle_mesh` − VmRSS before it, the high-water mark
  being reset just before (`/proc/self/clear_refs` ← 5, Linux ≥ 4.0). Open3D's CPU allocator is
  plain malloc/free, so RSS is its C++ allocations as touched pages (allocated but untouched
  pages do not count, as they cost nothing).

  Args:
    frames: the frames (depth in metres, 0 = hole; camera-to-world poses).
    voxel_size: metres.
    trunc_voxels: truncation in voxels (trunc = trunc_voxels · voxel_size).
    block_resolution: R, voxels per block edge.
    weighting: only "constant" (1 per observation) is what Open3D does.
    max_weight: only None (Open3D does not cap weights).
    depth_max: depths above it are ignored (Open3D: > depth_max in integrate, ≥ in the block
      selection).
    repeats: timed passes and timed mesh extractions.
    weight_threshold: see above.
    block_count: initial hash map capacity of the warm-up pass (None: 1024).
    memory: measure RSS in a child process (about a second more).

  Returns:
    dict; status "ok" with `integrate_ms_per_frame` (block selection + integration; split in
    `touch_ms_per_frame`, `integrate_only_ms_per_frame`), `integrate_ms_pass_medians`,
    `sequence_ms` (median over passes of the whole sequence), `mesh_ms`, `mesh_ms_all`,
    `vertices` (V, 3) float64, `faces` (F, 3) int64, `num_triangles`, `num_vertices`,
    `num_blocks`, `num_voxels` (allocated), `num_voxels_observed` (weight > 0), `max_weight`
    seen, `attributes_valid` (see `_check_attributes`), `capacity_blocks`, `bytes_keys`,
    `bytes_values`, `bytes_heap`, `bytes_buffers` (their sum, at capacity), `bytes_per_voxel`
    (= bytes_buffers / num_voxels), `bytes_per_voxel_at_size` (the same for the allocated
    blocks only), `attr_bytes_per_voxel` (tsdf + weight: 8), and with `memory`
    `grid_rss_growth_bytes`, `mesh_peak_bytes`, `mesh_retained_bytes`, `mesh_rss_before_bytes`,
    `hwm_reset`, `memory_method`; plus the settings. Status "not installed" when open3d cannot
    be imported, "unsupported" (with `reason`) for another weighting or a weight cap.
  """
  if weighting != "constant":
    return {"status": "unsupported",
            "reason": f"weighting={weighting!r}: Open3D's integrate adds weight 1 per observation "
                      "and takes no weight argument"}
  if max_weight is not None:
    return {"status": "unsupported", "reason": "Open3D's integrate does not cap weights"}
  o3d = _import_open3d()
  if o3d is None:
    return {"status": "not installed"}
  num_frames, height, width = frames.depth.shape
  intrinsic, depths, extrinsics = _inputs(o3d, frames.depth, frames.poses, _camera(frames))
  args = (intrinsic, depths, extrinsics, depth_max, trunc_voxels)

  grid = _new_grid(o3d, voxel_size, block_resolution, block_count or 1024)
  _integrate_all(o3d, grid, *args)                        # warm-up pass
  capacity = int(grid.hashmap().capacity())
  touch, integ, pass_medians, sequences = [], [], [], []
  for _ in range(repeats):
    del grid
    grid = _new_grid(o3d, voxel_size, block_resolution, capacity)
    t, i = _integrate_all(o3d, grid, *args)
    touch += t
    integ += i
    per_frame = np.add(t, i)
    pass_medians.append(1e3 * float(np.median(per_frame)))
    sequences.append(1e3 * float(np.sum(per_frame)))
  per_frame = np.add(touch, integ)

  mesh = grid.extract_triangle_mesh(weight_threshold=weight_threshold)      # warm-up
  mesh_times = []
  for _ in range(repeats):
    del mesh
    t0 = time.perf_counter()
    mesh = grid.extract_triangle_mesh(weight_threshold=weight_threshold)
    mesh_times.append(time.perf_counter() - t0)
  vertices = mesh.vertex.positions.numpy().astype(np.float64)
  faces = mesh.triangle.indices.numpy().astype(np.int64)

  hashmap = grid.hashmap()
  num_blocks = int(hashmap.size())
  capacity = int(hashmap.capacity())
  voxels_per_block = block_resolution ** 3
  num_voxels = num_blocks * voxels_per_block
  keys = hashmap.key_tensor().numpy()
  values = [hashmap.value_tensor(i).numpy() for i in range(2)]
  bytes_keys = int(keys.nbytes)
  bytes_values = int(sum(v.nbytes for v in values))
  bytes_heap = 4 * capacity                                 # uint32 per entry (HashBackendBuffer)
  bytes_buffers = bytes_keys + bytes_values + bytes_heap
  bytes_per_block = bytes_buffers / capacity
  tsdf, weight = _active_attributes(grid)

  out = {"status": "ok", "version": o3d.__version__,
         "method": "t.geometry.VoxelBlockGrid integrate + extract_triangle_mesh (CPU)",
         "voxel_size": voxel_size, "trunc_voxels": trunc_voxels,
         "trunc_m": trunc_voxels * voxel_size, "block_resolution": block_resolution,
         "weighting": weighting, "max_weight_cap": max_weight, "depth_max": depth_max,
         "weight_threshold": weight_threshold, "num_frames": num_frames,
         "height": height, "width": width, "repeats": repeats,
         "integrate_ms_per_frame": 1e3 * float(np.median(per_frame)),
         "touch_ms_per_frame": 1e3 * float(np.median(touch)),
         "integrate_only_ms_per_frame": 1e3 * float(np.median(integ)),
         "integrate_ms_pass_medians": pass_medians,
         "sequence_ms": float(np.median(sequences)),
         "mesh_ms": 1e3 * float(np.median(mesh_times)),
         "mesh_ms_all": [1e3 * t for t in mesh_times],
         "vertices": vertices, "faces": faces,
         "num_vertices": int(vertices.shape[0]), "num_triangles": int(faces.shape[0]),
         "num_blocks": num_blocks, "num_voxels": num_voxels,
         "num_voxels_observed": int(np.count_nonzero(weight > 0)),
         "max_weight": float(weight.max()) if weight.size else 0.0,
         "attributes_valid": _check_attributes(tsdf, weight, num_frames),
         "capacity_blocks": capacity, "bytes_keys": bytes_keys, "bytes_values": bytes_values,
         "bytes_heap": bytes_heap, "bytes_buffers": bytes_buffers,
         "bytes_per_voxel": bytes_buffers / max(num_voxels, 1),
         "bytes_per_voxel_at_size": bytes_per_block / voxels_per_block,
         "attr_bytes_per_voxel": bytes_values / capacity / voxels_per_block}
  del keys, values, tsdf, weight, mesh, grid
  if memory:
    out.update(_mesh_memory(frames, voxel_size=voxel_size, block_resolution=block_resolution,
                            block_count=capacity, depth_max=depth_max, trunc_voxels=trunc_voxels,
                            weight_threshold=weight_threshold))
    out["memory_method"] = (
        "fresh process (multiprocessing spawn): grid = VmRSS after integrating all frames − "
        "before; mesh peak = VmHWM after extract_triangle_mesh − VmRSS before, VmHWM reset by "
        "/proc/self/clear_refs just before" if out["hwm_reset"] else
        "fresh process: VmHWM could not be reset, mesh peak = process high-water mark − VmRSS "
        "before extraction (includes integration's peak: an upper bound)")
  return out
