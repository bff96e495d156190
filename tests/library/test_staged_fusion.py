"""The `Mapper`'s staged frame: `fusion.prepare_frame` (compiled once) then each table's half
(`fusion.fuse_prepared_unchecked`, `tsdf.integrate_blocks_unchecked`), so that a growth
recompiles only the grown table's half, and the host (NumPy) rehash a growth runs on the CPU.
The map comes out as `fuse_frame`'s, bit for bit."""

import threading
import time

import jax
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import fusion
from jaxfusion import mapper as mapper_lib
from jaxfusion import state as state_lib
from jaxfusion import tsdf

K = 5
CAMERA = jf.Camera(24.0, 24.0, 19.5, 14.5)


def _frames(num_frames, seed=0):
  """A walk past rough walls at 5 cm voxels: ~1 100 new voxels and ~120 new blocks a frame."""
  rng = np.random.default_rng(seed)
  depth = rng.uniform(1.0, 6.0, (num_frames, 30, 40)).astype(np.float32)
  depth[:, :2] = 0.0
  depth[:, 5, 7] = np.nan                                 # a hole of another kind
  poses = np.tile(np.eye(4, dtype=np.float32), (num_frames, 1, 1))
  poses[:, 0, 3] = np.arange(num_frames) * 0.8
  probs = rng.dirichlet(np.ones(K), (num_frames, 30, 40)).astype(np.float32)
  probs[:, 3, 3] = [1.0, 0.0, 0.0, 0.0, 0.0]              # exactly 0 and 1
  var = rng.uniform(0.0, 0.05, (num_frames, 30, 40, K)).astype(np.float32)
  return [jf.Frame(depth[t], poses[t], probs[t], var[t]) for t in range(num_frames)]


def _blocks(layer) -> dict:
  keys = np.asarray(layer.block_keys)
  stored = keys[:, 0] != jf.hashing.EMPTY
  sdf, weight = np.asarray(layer.sdf), np.asarray(layer.weight)
  return {tuple(k): (s, w) for k, s, w in zip(keys[stored], sdf[stored], weight[stored])}


def _assert_same_maps(a, b):
  va, vb = jf.read_map(a), jf.read_map(b)
  assert set(va) == set(vb)
  for key in va:
    np.testing.assert_array_equal(va[key], vb[key], err_msg=key)
  assert int(a.num_dropped) == 0 == int(b.num_dropped)
  if a.geometry is not None:
    ga, gb = _blocks(a.geometry), _blocks(b.geometry)
    assert ga.keys() == gb.keys()
    for key, (sdf, weight) in ga.items():
      np.testing.assert_array_equal(sdf, gb[key][0])
      np.testing.assert_array_equal(weight, gb[key][1])


_WATCHED = (("prepare", fusion.prepare_frame), ("semantic", fusion.fuse_prepared_donating),
            ("geometry", tsdf.integrate_blocks_donating), ("rehash", state_lib.grown_map),
            ("block rehash", tsdf.grown_tsdf), ("move", jf.hashing.moved_rows))


def _growing_walk(rule, frames, before_frame=lambda: None):
  """Both layers (and free space) grow at frame 1; what each watched program compiled.
  `before_frame()` is called before each frame is fused."""
  before = {name: fun._cache_size() for name, fun in _WATCHED}
  mapper = jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=2**12, free_space=True,
                     geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=2**9))
  for frame in frames:
    before_frame()
    mapper.fuse(frame, CAMERA)
  assert mapper.growths == [(1, 2**12, 2**14)]
  assert mapper.geometry_growths == [(1, 2**9, 2**11)]
  return mapper, {name: fun._cache_size() - before[name] for name, fun in _WATCHED}


def _fixed_map(rule, frames):
  """The walk's frames fused with `fuse_frame` into a map of its final capacities."""
  fixed = jf.init_map(capacity=2**14, num_classes=K, voxel_size=0.05, rule=rule,
                      free_space=True,
                      geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=2**11))
  for frame in frames:
    fixed = jf.fuse_frame(fixed, frame, CAMERA, rule)
  return fixed


def test_a_growing_mapper_equals_fuse_frame_and_compiles_each_grown_half_once(monkeypatch):
  """Both layers (and free space) grow at frame 1 (frame 0 leaves room, so the prepared
  geometry settings must outlive the layer's donation); the map equals a map of the final
  capacities fused frame by frame with `fuse_frame`, bit for bit, and across the growths the
  frame's half compiled once, the rehashes not at all (host NumPy). Each growth compiles the
  grown table's half for the shapes the rehash will have while a worker thread rehashes: both
  rehashes run off the calling thread, one program is compiled (or fetched from the persistent
  cache) within each overlap, and the growing frame's calls then compile nothing (a compile
  for shapes other than the rehash's would be followed by the call's own)."""
  on_main = []
  for module, name in ((state_lib, "grow_map"), (tsdf, "grow_tsdf")):
    def recorded(*args, _original=getattr(module, name), _name=name, **kwargs):
      on_main.append((_name, threading.current_thread() is threading.main_thread()))
      return _original(*args, **kwargs)
    monkeypatch.setattr(module, name, recorded)
  requests, overlapped = [0], []
  def counted(grow, compile_half, _original=mapper_lib._grown_while_compiling):
    before = requests[-1]
    grown = _original(grow, compile_half)
    overlapped.append(requests[-1] - before)
    return grown
  monkeypatch.setattr(mapper_lib, "_grown_while_compiling", counted)
  def on_duration(event, *_, **__):
    # Timed around every compile request, whether XLA compiles or the persistent cache serves.
    if event == "/jax/core/compile/backend_compile_duration":
      requests[-1] += 1
  rule = jf.rules.robust(beta=0.3)
  frames = _frames(5)
  jax.clear_caches()          # the growing frame compiles its halves afresh, as in a new process
  jax.monitoring.register_event_duration_secs_listener(on_duration)
  try:
    mapper, grown = _growing_walk(rule, frames, before_frame=lambda: requests.append(0))
  finally:
    jax.monitoring.unregister_event_duration_listener(on_duration)
  assert grown == {"prepare": 1, "semantic": 2, "geometry": 2, "rehash": 0, "block rehash": 0,
                   "move": 0}
  assert sorted(on_main) == [("grow_map", False), ("grow_tsdf", False)]
  # One program compiled within each growth's overlap, none by the frame's calls after it.
  assert overlapped == [1, 1] and requests[2] == 2 and requests[3:] == [0, 0, 0], (
      overlapped, requests)
  _assert_same_maps(mapper.state, _fixed_map(rule, frames))


def test_tables_whose_rows_move_with_a_compiled_program_do_not_grow_in_numpy(monkeypatch):
  """`grows_in_numpy`: small host tables rehash in NumPy alone (so a growth may overlap them
  with its compile); from `hashing.HOST_MOVE_BYTES` of grown arrays the rows move with a
  compiled program, so the `Mapper` rehashes and compiles one after the other (the walk of
  `test_rows_moved_as_large_tables_are_compile_no_table_half_again` takes that path)."""
  rule = jf.rules.robust(beta=0.3)
  state = jf.init_map(capacity=2**12, num_classes=K, voxel_size=0.05, rule=rule,
                      geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=2**9))
  assert state_lib.grows_in_numpy(state, 2**14) and tsdf.grows_in_numpy(state.geometry, 2**11)
  monkeypatch.setattr(jf.hashing, "HOST_MOVE_BYTES", 0)    # every table counts as large
  assert not state_lib.grows_in_numpy(state, 2**14)
  assert not tsdf.grows_in_numpy(state.geometry, 2**11)


def test_growing_while_compiling_runs_both_and_raises_either_error():
  """`_grown_while_compiling`: the rehash's result, with an error of either side raised once
  both have finished."""
  done = []
  def slow_grow():
    time.sleep(0.05)
    done.append(("grow", threading.current_thread() is threading.main_thread()))
    return "grown"
  assert mapper_lib._grown_while_compiling(slow_grow, lambda: done.append(("compile", True))) \
      == "grown"
  assert sorted(done) == [("compile", True), ("grow", False)]
  def failing_grow():
    time.sleep(0.05)
    raise ValueError("3 blocks found no slot")
  done.clear()
  with pytest.raises(ValueError, match="found no slot"):
    mapper_lib._grown_while_compiling(failing_grow, lambda: done.append("compile"))
  assert done == ["compile"]
  def failing_compile():
    raise RuntimeError("compile failed")
  with pytest.raises(RuntimeError, match="compile failed"):
    mapper_lib._grown_while_compiling(slow_grow, failing_compile)
  assert done[-1] == ("grow", False)      # the rehash finished before the error was raised


@pytest.mark.slow   # the walk twice (its first, fresh, compiles what the second must not)
def test_rows_moved_as_large_tables_are_compile_no_table_half_again(monkeypatch):
  """The same walk with the rows moved as large tables' are (`hashing.moved_rows`, once per
  layer's growth): the same map, and not one program more for the halves, so the moved arrays
  are placed as the old ones (a committed copy would compile each table half again)."""
  rule = jf.rules.robust(beta=0.3)
  frames = _frames(5)
  _growing_walk(rule, frames)          # the halves at both capacities, compiled
  monkeypatch.setattr(jf.hashing, "HOST_MOVE_BYTES", 0)
  mapper, grown = _growing_walk(rule, frames)
  assert grown == {"prepare": 0, "semantic": 0, "geometry": 0, "rehash": 0, "block rehash": 0,
                   "move": 2}
  _assert_same_maps(mapper.state, _fixed_map(rule, frames))


def test_the_host_rehash_equals_the_compiled_one():
  """Rows moved in NumPy and by `hashing.moved_rows` (`on_device`) alike."""
  rule = jf.rules.bayes()
  frames = _frames(2)
  state = jf.init_map(capacity=2**12, num_classes=K, voxel_size=0.05, rule=rule,
                      free_space=True,
                      geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=2**9))
  for frame in frames:
    state = jf.fuse_frame(state, frame, CAMERA, rule)
  prior = state_lib.prior_row(state, rule)
  device, device_lost = state_lib.grown_map(state, prior, capacity=2**14)
  # 2**12 blocks: not the growing walk's 2**11, whose moved_rows entry it counts.
  compiled_blocks = _blocks(tsdf.grown_tsdf(state.geometry, capacity=2**12)[0])
  assert int(device_lost) == 0 and compiled_blocks.keys() == _blocks(state.geometry).keys()
  for on_device in (False, True):
    host, lost = state_lib.grown_map_host(state, prior, capacity=2**14, on_device=on_device)
    assert lost == 0 and host.capacity == 2**14
    assert int(host.num_occupied) == int(state.num_occupied)
    assert not np.asarray(host.claims).any() and host.claims.shape == (2**14,)
    _assert_same_maps(host.replace(geometry=None), device.replace(geometry=None))
    _assert_same_maps(host.replace(geometry=None), state.replace(geometry=None))
    # Each voxel keeps its occupancy log-odds and hits; every other slot holds the prior.
    for grown in (host, device):
      old_keys, new_keys = np.asarray(state.keys), np.asarray(grown.keys)
      before = {tuple(k): i for i, k in enumerate(old_keys) if k[0] != jf.hashing.EMPTY}
      after = {tuple(k): i for i, k in enumerate(new_keys) if k[0] != jf.hashing.EMPTY}
      assert before.keys() == after.keys() and before
      old_at, new_at = list(before.values()), [after[k] for k in before]
      for old, new in ((state.free_space.log_odds, grown.free_space.log_odds),
                       (state.hits, grown.hits)):
        np.testing.assert_array_equal(np.asarray(old)[old_at], np.asarray(new)[new_at])
      empty = np.ones(2**14, bool)
      empty[new_at] = False
      assert not np.asarray(grown.free_space.log_odds)[empty].any()
      assert not np.asarray(grown.hits)[empty].any()
      for name, row in prior.items():
        np.testing.assert_array_equal(np.asarray(grown.rows[name])[empty],
                                      np.broadcast_to(np.asarray(row), (empty.sum(), K)))
    blocks, blocks_lost = tsdf.grown_tsdf_host(state.geometry, capacity=2**12,
                                               on_device=on_device)
    assert blocks_lost == 0 and blocks.capacity == 2**12
    a = _blocks(blocks)
    assert a.keys() == compiled_blocks.keys()
    for key, (sdf, weight) in a.items():
      np.testing.assert_array_equal(sdf, compiled_blocks[key][0])
      np.testing.assert_array_equal(weight, compiled_blocks[key][1])
  # Too small a table: the voxels that find no slot are counted (and grow_map refuses).
  _, lost = state_lib.grown_map_host(state.replace(geometry=None), prior, capacity=2**12)
  assert lost == 0
  small = state.replace(max_probes=1, geometry=None)
  _, lost = state_lib.grown_map_host(small, prior, capacity=2**12)
  assert lost > 0


def test_the_staged_halves_refuse_what_they_cannot_fuse():
  rule = jf.rules.bayes()
  frame = _frames(1)[0]
  gated = jf.init_map(capacity=2**10, num_classes=K, voxel_size=0.05, rule=rule,
                      geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=2**6,
                                                  gate_semantics=True))
  with pytest.raises(ValueError, match="gate_semantics"):
    fusion.prepare_frame_unchecked(gated.voxel_size, frame, CAMERA, rule,
                                   tsdf.settings_only(gated.geometry))
  with pytest.raises(ValueError, match="geometry=None"):
    fusion.fuse_prepared_unchecked(gated, None, CAMERA, rule)
  # A gated layer makes the Mapper fuse each frame as one fuse_frame.
  mapper = jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=2**10,
                     geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=2**9,
                                                 gate_semantics=True))
  before = (fusion.prepare_frame._cache_size(), fusion.fuse_frame_donating._cache_size())
  mapper.fuse(frame, CAMERA)
  assert (fusion.prepare_frame._cache_size(), fusion.fuse_frame_donating._cache_size()) == (
      before[0], before[1] + 1)
  assert int(mapper.state.num_occupied) > 0 and int(mapper.state.geometry.num_blocks) > 0


@pytest.mark.slow   # ~10 s; the staged halves' other tests keep the main tier's share
def test_a_context_rule_with_colour_fuses_through_the_staged_frame_as_fuse_frame():
  """A rule that reads per-pixel context (here from the colour image, docs/equations.md §2.5)
  gets it in the semantic half from the prepared frame's arrays: the same map."""
  rule = jf.rules.learned(context=("depth_edge", "luminance"))
  rng = np.random.default_rng(3)
  frames = [f._replace(rgb=rng.integers(0, 256, (30, 40, 3), dtype=np.uint8))
            for f in _frames(2, seed=3)]
  mapper = jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=2**12)
  fixed = jf.init_map(capacity=2**12, num_classes=K, voxel_size=0.05, rule=rule)
  for frame in frames:
    mapper.fuse(frame, CAMERA)
    fixed = jf.fuse_frame(fixed, frame, CAMERA, rule)
  _assert_same_maps(mapper.state, fixed)


def test_a_frame_whose_room_is_sure_waits_for_nothing_the_frame_before_computes(monkeypatch):
  """In a plain loop the host checks and dispatches a frame while the one before still runs:
  the room check counts that frame by bounds (its pixels, the blocks recent frames added), so
  while they settle it nothing is read from the device. A device that is always behind is
  simulated by `mapper._is_ready` (no count is ever computed yet), and every read the room
  checks make goes through `mapper._read`, which fails here while armed. A map whose bounds
  do not settle it reads (caught: the first half of the test can fail), and a walk that grows
  with every frame behind still grows before it fills and ends as `fuse_frame`'s map, bit
  for bit."""
  rule = jf.rules.robust(beta=0.3)
  frames = _frames(5)
  monkeypatch.setattr(mapper_lib, "_is_ready", lambda x: False)
  armed, read = [False], mapper_lib._read

  def guarded_read(x):
    if armed[0]:
      raise RuntimeError("the room check read a device count")
    return read(x)

  monkeypatch.setattr(mapper_lib, "_read", guarded_read)

  def fuse_second_frame_unread(capacity):
    mapper = jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=capacity,
                       geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=2**14))
    mapper.fuse(frames[0], CAMERA)
    armed[0] = True
    try:
      mapper.fuse(frames[1], CAMERA)
    finally:
      armed[0] = False
    return mapper

  roomy = fuse_second_frame_unread(2**16)      # 1 100 voxels a frame in 32 768 of room
  assert len(roomy._in_flight) == 2 and roomy.growths == []
  with pytest.raises(RuntimeError, match="read a device count"):
    fuse_second_frame_unread(2**12)            # 2 048 of room: frame 0's count is needed

  # The first test's walk (its programs are compiled already), every frame behind.
  mapper, _ = _growing_walk(rule, frames)
  assert len(mapper._in_flight) <= 2
  _assert_same_maps(mapper.state, _fixed_map(rule, frames))
