"""Many maps in one compiled call: `vmap` over sequences and over rule grids, sharded over devices.

Three batch shapes, each one jitted call (shape legend: B sequences, R rules, T frames, H×W
pixels, K classes, C slots):

    fuse_batch(frames (B, T, H, W, ·), camera, rule)          ─► MapState with leading (B,)
    fuse_sweep(frames (T, H, W, ·), camera, rules (R,))        ─► MapState with leading (R,)
    fuse_sweep(frames (B, T, H, W, ·), camera, rules (R,))     ─► MapState with leading (R, B)

Every map of a batch has the same capacity C (the arrays are dense). Each map starts empty and is
fused exactly as `init_map` followed by `fuse_sequence` would fuse it.

**Ragged batches.** `stack_sequences` pads sequences of different lengths (and image sizes) to
one `(B, T_max, H_max, W_max)` stack and returns a `(B, T_max)` mask. Padding is provably neutral:
a masked frame's depth is set to 0 inside the kernel, and a pixel with depth 0 is invalid, touches
no voxel and changes no state (the engine skips it before grouping); padded pixels (bottom / right)
have depth 0 too, and the pixels kept keep their (u, v), so their rays do not change. With
free-space clearing on (`fuse_batch(..., free_space=True)`) a pixel of depth 0 sees no surface,
so padding marks no voxel free either.

**Devices.** Pass `mesh=make_mesh()` to shard the leading batch axis over all devices with
`jax.shard_map`: every device fuses its slice of sequences (or of rules) on its own, with the same
per-map program as on one device. Inputs are placed with `NamedSharding(mesh, P("batch"))`; a
batch that does not divide the device count is padded (masked sequences, repeated rules) and the
padding is cut off again. On several hosts call `jax.distributed.initialize()` first in every
process, then run the same script with the same inputs in every process: `make_mesh()` then spans
the devices of all hosts, each process builds only its own shards
(`jax.make_array_from_callback`), and `gather` returns the full result on every host.
"""

import functools
import math
from typing import Optional, Sequence, Union

import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from jaxfusion import camera as camera_lib
from jaxfusion import distributed
from jaxfusion import free_space as free_space_lib
from jaxfusion import fusion
from jaxfusion import rules as rules_lib
from jaxfusion import state as state_lib
from jaxfusion import tsdf
from jaxfusion import validation
from jaxfusion.rules import base as rules_base

BATCH_AXIS = "batch"

CameraArg = Union[camera_lib.Camera, Sequence[camera_lib.Camera]]


# --- ragged batches ---------------------------------------------------------------------------
def stack_sequences(sequences: Sequence[fusion.Frame], *, pad: bool = True
                    ) -> tuple[fusion.Frame, np.ndarray]:
  """Stacks B frame sequences into one batch, padding ragged lengths and image sizes.

  Args:
    sequences: B Frames, each with a leading time axis: `depth (T_b, H_b, W_b)`,
      `T_world_cam (T_b, 4, 4)`, `probs (T_b, H_b, W_b, K)`, `var (T_b, H_b, W_b, K)` or None
      (all with var, or all without). K must agree.
    pad: pad to the longest sequence and the largest image (bottom / right). With `pad=False`
      sequences of different lengths or image sizes raise instead.

  Returns:
    `(frames, mask)`: a Frame of NumPy arrays with leading `(B, T_max)` axes (padded frames and
    pixels have depth 0, identity pose, uniform probabilities, zero variance) and a
    `(B, T_max) bool` mask, True for real frames. Fusing the padded batch gives the same maps
    as fusing each sequence alone.

  Raises:
    ValueError: an empty list, mismatched K, some sequences with var and some without, or
      (with `pad=False`) different lengths / image sizes.
  """
  if not sequences:
    raise ValueError("stack_sequences needs at least one sequence")
  for i, seq in enumerate(sequences):
    if not isinstance(seq, fusion.Frame):
      raise TypeError(f"sequence {i} must be a jaxfusion.Frame with a leading time axis; got "
                      f"{type(seq).__name__}")
    if np.ndim(seq.depth) != 3 or np.ndim(seq.probs) != 4:
      raise ValueError(f"sequence {i}: expected depth (T, H, W) and probs (T, H, W, K); got "
                       f"{np.shape(seq.depth)} and {np.shape(seq.probs)}")
  num_classes = {np.shape(s.probs)[-1] for s in sequences}
  if len(num_classes) != 1:
    raise ValueError(f"all sequences must have the same number of classes K; got "
                     f"{sorted(num_classes)}")
  (num_classes,) = num_classes
  has_var = {s.var is not None for s in sequences}
  if len(has_var) != 1:
    raise ValueError("either every sequence has var or none has")
  for i, seq in enumerate(sequences):
    try:
      validation.check_frame(seq, num_classes=num_classes, requires_var=False,
                             rule_name="", batch_dims=1)
    except ValueError as err:
      raise ValueError(f"sequence {i}: {err}") from None
  lengths = [np.shape(s.depth)[0] for s in sequences]
  sizes = [tuple(np.shape(s.depth)[1:]) for s in sequences]
  if not pad and (len(set(lengths)) > 1 or len(set(sizes)) > 1):
    raise ValueError(
        f"sequences differ in length {lengths} or image size {sizes}; pass pad=True to pad "
        "them (padding is masked and does not change the maps), or batch equal sequences only")
  batch, t_max = len(sequences), max(lengths)
  h_max, w_max = max(s[0] for s in sizes), max(s[1] for s in sizes)
  depth = np.zeros((batch, t_max, h_max, w_max), np.float32)
  poses = np.tile(np.eye(4, dtype=np.float32), (batch, t_max, 1, 1))
  probs = np.full((batch, t_max, h_max, w_max, num_classes), 1.0 / num_classes, np.float32)
  var = np.zeros_like(probs) if has_var == {True} else None
  has_rgb = {getattr(s, "rgb", None) is not None for s in sequences}
  if len(has_rgb) != 1:
    raise ValueError("either every sequence has rgb or none has")
  rgb = None
  if has_rgb == {True}:
    rgb_dtypes = {np.asarray(s.rgb).dtype for s in sequences}
    rgb = np.zeros((batch, t_max, h_max, w_max, 3),
                   np.uint8 if rgb_dtypes == {np.dtype(np.uint8)} else np.float32)
  mask = np.zeros((batch, t_max), bool)
  for b, seq in enumerate(sequences):
    t, (h, w) = lengths[b], sizes[b]
    depth[b, :t, :h, :w] = np.asarray(seq.depth, np.float32)
    poses[b, :t] = np.asarray(seq.T_world_cam, np.float32)
    probs[b, :t, :h, :w] = np.asarray(seq.probs, np.float32)
    if var is not None:
      var[b, :t, :h, :w] = np.asarray(seq.var, np.float32)
    if rgb is not None:
      rgb[b, :t, :h, :w] = np.asarray(seq.rgb, rgb.dtype)
    mask[b, :t] = True
  return fusion.Frame(depth, poses, probs, var, rgb), mask


# --- the per-map kernel and its batched forms ------------------------------------------------
def fuse_masked(frames: fusion.Frame, mask: jax.Array, camera: camera_lib.Camera,
                rule: rules_base.FusionRule, *, capacity: int, num_classes: int,
                voxel_size: float, max_probes: int, geometry=None,
                free_space=False) -> state_lib.MapState:
  """One map, pure and jittable: `init_map` then `fuse_sequence` of the frames where `mask`.

  Args:
    frames: `depth (T, H, W)`, `T_world_cam (T, 4, 4)`, `probs (T, H, W, K)`, `var` or None.
    mask: `(T,) bool`; a False frame gets depth 0 and so touches nothing.
    camera: intrinsics.
    rule: one (unstacked) FusionRule.
    capacity: slots C (a power of two).
    num_classes: K.
    voxel_size: voxel edge in metres.
    max_probes: hash probe bound.
    geometry: a `tsdf.TSDFConfig` for a geometry layer, or None.
    free_space: free-space clearing (`init_map`'s option: False, True or a `FreeSpaceConfig`).

  Returns:
    The fused MapState.
  """
  assert frames.depth.ndim == 3 and mask.shape == frames.depth.shape[:1], (
      frames.depth.shape, mask.shape)
  state = state_lib.init_map(capacity=capacity, num_classes=num_classes, voxel_size=voxel_size,
                             rule=rule, max_probes=max_probes, geometry=geometry,
                             free_space=free_space)
  return fusion.fuse_sequence_unchecked(state, mask_frames(frames, mask), camera, rule)


def mask_frames(frames: fusion.Frame, mask: jax.Array) -> fusion.Frame:
  """The frames with depth 0 (touching nothing) where `mask (T,) bool` is False."""
  depth = jnp.where(mask[:, None, None], jnp.asarray(frames.depth, jnp.float32), 0.0)
  return frames._replace(depth=depth)


def map_over(fn, *, frames_axis: bool, rule_axis: bool, camera_axis: bool):
  """Lifts `fn(frames, mask, camera, rule) -> pytree` to a batch.

  The sequence axis (`frames_axis`, with the camera batched too if `camera_axis`) is inner, the
  rule axis outer: the result has leading `(R, B)`, `(R,)`, `(B,)` or no axes.
  """
  if frames_axis:
    fn = jax.vmap(fn, in_axes=(0, 0, 0 if camera_axis else None, None))
  if rule_axis:
    fn = jax.vmap(fn, in_axes=(None, None, None, 0))
  return fn


def shard_leading(fn, mesh: Optional[Mesh], sharded: tuple):
  """`fn` as is (mesh None), or under `jax.shard_map` with the leading axis of the arguments
  flagged in `sharded` split over the mesh's `BATCH_AXIS`, and every output split likewise."""
  if mesh is None:
    return fn
  specs = tuple(PartitionSpec(BATCH_AXIS) if s else PartitionSpec() for s in sharded)
  return jax.shard_map(fn, mesh=mesh, in_specs=specs, out_specs=PartitionSpec(BATCH_AXIS),
                       check_vma=False)


@functools.partial(jax.jit, static_argnames=(
    "capacity", "num_classes", "max_probes", "frames_axis", "rule_axis", "camera_axis", "mesh",
    "geometry", "free_space"))
def _fuse_many(frames, mask, camera, rule, voxel_size, *, capacity, num_classes, max_probes,
               frames_axis, rule_axis, camera_axis, mesh, geometry=None, free_space=False):
  # `voxel_size` is traced, not static: as a compile-time constant XLA may fold `x / s` into
  # `x · (1/s)`, whose rounding puts far-away points (|x| ≳ 10⁴ voxels) in other voxels than
  # `fuse_frame` / `fuse_sequence` (which get it at run time) put them.
  one = functools.partial(fuse_masked, capacity=capacity, num_classes=num_classes,
                          voxel_size=voxel_size, max_probes=max_probes, geometry=geometry,
                          free_space=free_space)
  fn = map_over(one, frames_axis=frames_axis, rule_axis=rule_axis, camera_axis=camera_axis)
  sharded = ((frames_axis and not rule_axis,) * 2 + (camera_axis and not rule_axis,)
             + (rule_axis,))
  return shard_leading(fn, mesh, sharded)(frames, mask, camera, rule)


# --- devices -------------------------------------------------------------------------------------
def make_mesh(num_devices: Optional[int] = None) -> Mesh:
  """A one-axis mesh named `BATCH_AXIS` over the first `num_devices` devices (default: all
  devices of all processes, after `jax.distributed.initialize()` on several hosts)."""
  devices = jax.devices()
  num_devices = len(devices) if num_devices is None else int(num_devices)
  if not 1 <= num_devices <= len(devices):
    raise ValueError(f"num_devices must lie in [1, {len(devices)}]; got {num_devices}")
  return Mesh(np.asarray(devices[:num_devices]), (BATCH_AXIS,))


def put_sharded(tree, mesh: Mesh, *, sharded: bool):
  """Places a pytree of host arrays on the mesh: leading axis split over `BATCH_AXIS`
  (`sharded`) or replicated. Works across hosts: every process builds only its own shards, so
  every process must pass the same full arrays."""
  spec = PartitionSpec(BATCH_AXIS) if sharded else PartitionSpec()
  sharding = NamedSharding(mesh, spec)

  def put(x):
    x = np.asarray(x)
    return jax.make_array_from_callback(x.shape, sharding, lambda index: x[index])

  return jax.tree.map(put, tree)


def gather(tree):
  """The full value of (possibly multi-host sharded) arrays as NumPy, on every process."""
  if jax.process_count() > 1:
    distributed.barrier("batch.gather")   # the processes may finish their shards far apart
    return multihost_utils.process_allgather(tree, tiled=True)
  return jax.device_get(tree)


def _on_host(x):
  """`x` as a NumPy array, or unchanged when it is a tracer (a call under `grad`, `vmap`, …)."""
  return x if isinstance(x, jax.core.Tracer) else np.asarray(x)


def pad_leading(tree, size: int, *, fill=None):
  """Pads the leading axis of every leaf to `size`, repeating the last item (or `fill`)."""

  def pad(x):
    x = _on_host(x)
    extra = size - x.shape[0]
    if extra == 0:
      return x
    xp = jnp if isinstance(x, jax.core.Tracer) else np
    tail = xp.repeat(x[-1:], extra, axis=0) if fill is None else xp.full(
        (extra,) + x.shape[1:], fill, x.dtype)
    return xp.concatenate([x, tail])

  return jax.tree.map(pad, tree)


def padded_size(n: int, mesh: Optional[Mesh]) -> int:
  """`n` rounded up to a multiple of the mesh's device count (`n` without a mesh)."""
  if mesh is None:
    return n
  return math.ceil(n / mesh.size) * mesh.size


# --- public entry points ----------------------------------------------------------------------
def check_batch_frames(frames, mask, rule, *, batch_dims, num_classes):
  """Validates a batch of frames (`batch_dims` leading axes) for `rule`; returns the bool mask
  of real frames (all True when `mask` is None). Raises TypeError/ValueError with the reason."""
  if not isinstance(frames, fusion.Frame):
    raise TypeError(f"frames must be a jaxfusion.Frame; got {type(frames).__name__}")
  lead = np.shape(frames.depth)[:batch_dims]
  if np.ndim(frames.depth) != 2 + batch_dims:
    what = "(B, T, H, W)" if batch_dims == 2 else "(T, H, W)"
    raise ValueError(f"depth must have shape {what}; got {np.shape(frames.depth)} (use "
                     "stack_sequences to batch sequences of different lengths or sizes)")
  flat = jax.tree.map(lambda x: _on_host(x).reshape((-1,) + np.shape(x)[batch_dims:]), frames)
  validation.check_frame(flat, num_classes=num_classes, requires_var=rule.requires_var,
                         rule_name=rule.name, batch_dims=1, context=rule.context)
  if mask is None:
    return np.ones(lead, bool)
  mask = np.asarray(mask)
  if mask.shape != lead or mask.dtype != bool:
    raise ValueError(f"mask must be a bool array of shape {lead}; got {mask.dtype} {mask.shape}")
  return mask


def camera_batch(camera: CameraArg, batch: Optional[int]):
  """(camera pytree, batched?) — one shared Camera, or one per sequence stacked."""
  if isinstance(camera, camera_lib.Camera):
    validation.check_camera(camera)
    return camera_lib.Camera(*(np.float32(c) for c in camera)), False
  cameras = list(camera)
  if batch is None or len(cameras) != batch:
    raise ValueError(f"pass one Camera, or one per sequence ({batch}); got {len(cameras)}")
  for c in cameras:
    validation.check_camera(c)
  return camera_lib.Camera(*np.asarray(cameras, np.float32).T), True


def num_stacked_rules(rules: rules_base.FusionRule) -> int:
  """R of a stack of rules: the common leading axis of its hyperparameter leaves (`(R,)`, or
  `(R, K)` for per-class values). Raises ValueError for an unstacked rule or ragged lengths."""
  leaves = jax.tree.leaves(rules.hparams)
  # Leading axis = rules; per-class hyperparameters (docs/equations.md §3.7) add a trailing (K,)
  # axis, and tables (the learned rule's per-class weights, GLFS) more.
  if not leaves or any(np.ndim(x) == 0 for x in leaves):
    raise ValueError("rules must be a stack of rules with hyperparameters, e.g. "
                     "rules.stack([rules.robust(beta=b) for b in betas]) or rule_grid(...)")
  sizes = {np.shape(x)[0] for x in leaves}
  if len(sizes) != 1:
    raise ValueError(f"stacked hyperparameters disagree in length: {sorted(sizes)}")
  return sizes.pop()


def _free_space_option(free_space):
  """`fuse_batch`'s `free_space`, checked (the one line `init_map` gives) and hashable."""
  if isinstance(free_space, free_space_lib.FreeSpaceConfig):
    return free_space
  if free_space is None or isinstance(free_space, bool):
    return bool(free_space)
  raise TypeError(f"free_space must be True, False or a jaxfusion.free_space.FreeSpaceConfig; "
                  f"got {type(free_space).__name__}")


def fuse_batch(frames: fusion.Frame, camera: CameraArg, rule: rules_base.FusionRule, *,
               capacity: int, voxel_size: float = 0.1, mask=None,
               max_probes: int = state_lib.DEFAULT_MAX_PROBES,
               mesh: Optional[Mesh] = None, geometry=None,
               free_space=False) -> state_lib.MapState:
  """Fuses B sequences into B maps of one capacity, in one compiled call.

  Args:
    frames: a Frame with leading `(B, T)` axes: `depth (B, T, H, W)`, `T_world_cam
      (B, T, 4, 4)`, `probs (B, T, H, W, K)`, `var (B, T, H, W, K)` or None. Use
      `stack_sequences` for ragged sequences.
    camera: one Camera for all sequences, or a list of B Cameras.
    rule: one FusionRule, applied to every sequence.
    capacity: slots C of every map (a power of two).
    voxel_size: voxel edge in metres.
    mask: `(B, T) bool`, False for padded frames (default: all True).
    max_probes: hash probe bound.
    mesh: shard the B sequences over this mesh's devices (see `make_mesh`); None: one device.
    geometry: a `tsdf.TSDFConfig`: every map carries a geometry layer of this configuration.
    free_space: free-space clearing in every map (`init_map`'s option: False, True or a
      `free_space.FreeSpaceConfig`; docs/equations.md §10).

  Returns:
    A MapState whose arrays have a leading `(B,)` axis; map b equals `fuse_sequence` of
    sequence b into an empty map (made with the same `free_space`). Take one out with
    `jax.tree.map(lambda x: x[b], states)`.
  """
  if not isinstance(rule, rules_base.FusionRule):
    raise TypeError(f"rule must be a FusionRule; got {type(rule).__name__}")
  if geometry is not None and not isinstance(geometry, tsdf.TSDFConfig):
    raise TypeError(f"geometry must be a jaxfusion.tsdf.TSDFConfig or None; got "
                    f"{type(geometry).__name__}")
  free_space = _free_space_option(free_space)
  num_classes = np.shape(frames.probs)[-1] if isinstance(frames, fusion.Frame) else None
  mask = check_batch_frames(frames, mask, rule, batch_dims=2, num_classes=num_classes)
  batch = mask.shape[0]
  camera, camera_axis = camera_batch(camera, batch)
  size = padded_size(batch, mesh)
  frames = pad_leading(jax.tree.map(_on_host, frames), size)
  mask = pad_leading(mask, size, fill=False)
  if camera_axis:
    camera = pad_leading(camera, size)
  if mesh is not None:
    frames, mask = put_sharded((frames, mask), mesh, sharded=True)
    camera = put_sharded(camera, mesh, sharded=camera_axis)
    rule = put_sharded(rule, mesh, sharded=False)
  states = _fuse_many(frames, mask, camera, rule, np.float32(voxel_size), capacity=capacity,
                      num_classes=num_classes, max_probes=max_probes, frames_axis=True,
                      rule_axis=False, camera_axis=camera_axis, mesh=mesh, geometry=geometry,
                      free_space=free_space)
  return jax.tree.map(lambda x: x[:batch], states) if size != batch else states


def fuse_sweep(frames: fusion.Frame, camera: CameraArg, rules: rules_base.FusionRule, *,
               capacity: int, voxel_size: float = 0.1, mask=None,
               max_probes: int = state_lib.DEFAULT_MAX_PROBES,
               mesh: Optional[Mesh] = None) -> state_lib.MapState:
  """Fuses one sequence (or a batch of B) with each of R stacked rules, in one compiled call.

  Args:
    frames: one sequence (`depth (T, H, W)`, …) or a batch (`depth (B, T, H, W)`, …).
    camera: one Camera, or a list of B Cameras for a batch.
    rules: R rules of one kind stacked with `rules.stack` (or from `rule_grid`).
    capacity: slots C of every map.
    voxel_size: voxel edge in metres.
    mask: `(T,)` or `(B, T) bool`, False for padded frames.
    max_probes: hash probe bound.
    mesh: shard the R rules over this mesh's devices; None: one device.

  Returns:
    A MapState with leading `(R,)` (one sequence) or `(R, B)` (a batch) axes.
  """
  if not isinstance(rules, rules_base.FusionRule):
    raise TypeError(f"rules must be a stacked FusionRule; got {type(rules).__name__}")
  num_rules = num_stacked_rules(rules)
  num_classes = np.shape(frames.probs)[-1] if isinstance(frames, fusion.Frame) else None
  batch_dims = 2 if np.ndim(getattr(frames, "depth", None)) == 4 else 1
  mask = check_batch_frames(frames, mask, rules, batch_dims=batch_dims,
                             num_classes=num_classes)
  camera, camera_axis = camera_batch(camera, mask.shape[0] if batch_dims == 2 else None)
  size = padded_size(num_rules, mesh)
  rules = pad_leading(rules, size)
  frames = jax.tree.map(_on_host, frames)
  if mesh is not None:
    frames, mask, camera = put_sharded((frames, mask, camera), mesh, sharded=False)
    rules = put_sharded(rules, mesh, sharded=True)
  states = _fuse_many(frames, mask, camera, rules, np.float32(voxel_size), capacity=capacity,
                      num_classes=num_classes, max_probes=max_probes,
                      frames_axis=batch_dims == 2, rule_axis=True, camera_axis=camera_axis,
                      mesh=mesh)
  return jax.tree.map(lambda x: x[:num_rules], states) if size != num_rules else states


def rule_grid(factory=None, **axes) -> tuple[rules_base.FusionRule, dict]:
  """The outer product of hyperparameter values as one stacked rule, for `fuse_sweep`.

  Args:
    factory: a rule factory taking keyword hyperparameters (default `rules.robust`, D+R).
    **axes: hyperparameter name → a list of values (a grid axis), or a scalar / string / bool
      (held fixed, e.g. `aggregate="mean"`, `regularize=False`).

  Returns:
    `(rules, grid)`: the stacked rule of R = Π len(axis) points, and a dict of `(R,)` NumPy
    arrays, the value of each swept hyperparameter at each point (row-major order).

  Example:
    >>> rules, grid = rule_grid(beta=np.linspace(0, 1, 32), eps=[1e-12, 1e-6])  # R = 64
  """
  factory = rules_lib.robust if factory is None else factory
  swept = {k: np.asarray(v, np.float64).reshape(-1) for k, v in axes.items()
           if not isinstance(v, (str, bool)) and np.ndim(v) > 0}
  fixed = {k: v for k, v in axes.items() if k not in swept}
  if not swept:
    raise ValueError("rule_grid needs at least one hyperparameter with a list of values")
  mesh_grid = np.meshgrid(*swept.values(), indexing="ij")
  grid = {k: g.reshape(-1) for k, g in zip(swept, mesh_grid)}
  points = len(next(iter(grid.values())))
  stacked = rules_base.stack([factory(**fixed, **{k: float(grid[k][i]) for k in grid})
                              for i in range(points)])
  return stacked, grid
