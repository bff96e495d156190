"""The benchmark suite: throughput per rule, scaling, scan and MC front end cost, peak memory,
and the NumPy / Open3D peers on the same frames in the same process.

Every timing is the median of `repeats` calls after one warm-up call, each ended with
`block_until_ready`; compile time is measured separately (ahead-of-time `lower().compile()`).
Results go to `<out_dir>/results.json` (for comparing runs) and `<out_dir>/results.md`.
"""

import dataclasses
import json
import os
import pathlib
import platform
import resource
import time
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np

import jaxfusion as jf
from bench import numpy_peer
from bench import open3d_peer
from bench import scene
from jaxfusion import fusion
from jaxfusion import hashing

HEADLINE = dict(height=480, width=640, num_classes=13, rule="robust_dr")


@dataclasses.dataclass
class Config:
  """What to measure. `full()` is the documented run, `quick()` a smoke run, `tiny()` a test."""
  resolutions: tuple = ((240, 320), (480, 640))
  classes: tuple = (7, 13, 40)
  rules: tuple = numpy_peer.RULES
  repeats: int = 15
  num_frames: int = 6
  capacity: int = 2**20
  pixel_scaling: tuple = ((120, 160), (240, 320), (480, 640), (960, 1280))
  capacities: tuple = (2**16, 2**18, 2**20, 2**22)
  fills: tuple = (0.0, 0.25, 0.5, 0.7)
  sequence_length: int = 8
  mc_samples: tuple = (1, 8, 32)
  # The whole pipeline: ((H, W), M samples, B frames per vmapped network call).
  pipeline: tuple = (((120, 160), 8, 8), ((120, 160), 32, 4), ((480, 640), 8, 2),
                     ((480, 640), 32, 1))
  pipeline_repeats: int = 3
  # The MC sampler with the layers before the first dropout shared, against every sample a full
  # pass: ((H, W), M).
  sampler: tuple = (((120, 160), 8), ((120, 160), 32), ((480, 640), 8))
  peer_repeats: int = 5
  voxel_size: float = 0.1

  @classmethod
  def full(cls):
    return cls()

  @classmethod
  def quick(cls):
    return cls(classes=(13,), repeats=5, num_frames=3, pixel_scaling=((120, 160), (240, 320),
                                                                    (480, 640)),
               capacities=(2**16, 2**20), fills=(0.0, 0.5), sequence_length=4,
               mc_samples=(1, 8, 32), peer_repeats=5,
               pipeline=(((120, 160), 8, 4), ((120, 160), 32, 2), ((480, 640), 8, 1),
                         ((480, 640), 32, 1)),
               pipeline_repeats=2, sampler=(((120, 160), 8), ((480, 640), 8)))

  @classmethod
  def tiny(cls):
    # One value per axis, chosen so that every stage reuses one compiled fuse_frame (headline
    # rule, K = 13, 24×32, capacity 2^12); fill 0.5 exercises the pre-filled table.
    return cls(resolutions=((24, 32),), classes=(13,), rules=("robust_dr",), repeats=1,
               num_frames=2, capacity=2**12, pixel_scaling=((24, 32),), capacities=(2**12,),
               fills=(0.5,), sequence_length=2, mc_samples=(2,), peer_repeats=1,
               pipeline=(((24, 32), 2, 2),), pipeline_repeats=1, sampler=(((24, 32), 2),))


def machine() -> dict:
  """The device and host the numbers were taken on."""
  dev = jax.devices()[0]
  try:
    load = os.getloadavg()
  except OSError:
    load = None
  cpu = platform.processor()
  try:
    with open("/proc/cpuinfo") as f:
      cpu = next((l.split(":", 1)[1].strip() for l in f if l.startswith("model name")), cpu)
  except OSError:
    pass
  return {
      "platform": dev.platform, "device_kind": dev.device_kind, "cpu": cpu,
      "cpu_count": os.cpu_count(), "load_avg_1_5_15": load, "jax": jax.__version__,
      "numpy": np.__version__, "python": platform.python_version(),
      "time": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
  }


def median_time(fn: Callable[[], object], repeats: int) -> float:
  """Median seconds of `fn()` over `repeats` calls after one warm-up call."""
  jax.block_until_ready(fn())
  times = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    times.append(time.perf_counter() - t0)
  return float(np.median(times))


class _Fuser:
  """Keeps a donated map and feeds it frames in turn (the map is never reused after donation)."""

  def __init__(self, state, frames, camera, rule, fn):
    self.state, self.frames, self.camera, self.rule, self.fn = state, frames, camera, rule, fn
    self.t = 0

  def __call__(self):
    self.state = self.fn(self.state, self.frames[self.t % len(self.frames)], self.camera,
                         self.rule)
    self.t += 1
    return self.state


def _memory(compiled) -> Optional[dict]:
  try:
    m = compiled.memory_analysis()
  except Exception:  # pylint: disable=broad-except
    return None
  if m is None:
    return None
  return {"argument_mb": m.argument_size_in_bytes / 2**20, "temp_mb": m.temp_size_in_bytes / 2**20,
          "output_mb": m.output_size_in_bytes / 2**20,
          "alias_mb": m.alias_size_in_bytes / 2**20,
          "peak_mb": (m.argument_size_in_bytes + m.temp_size_in_bytes + m.output_size_in_bytes
                      - m.alias_size_in_bytes) / 2**20}


def _device_frames(frames: scene.BenchFrames):
  return [jax.device_put(frames.frame(t)) for t in range(frames.depth.shape[0])]


def fuse_frame_row(frames, rule_name, *, capacity, repeats, voxel_size, public=True) -> dict:
  """Compile time, per-frame time, frames/s and points/s of fuse_frame on `frames`."""
  _, height, width, k = frames.probs.shape
  rule = jf.rules.by_name(rule_name)
  dev_frames = _device_frames(frames)
  state = jf.init_map(capacity=capacity, num_classes=k, voxel_size=voxel_size, rule=rule)
  t0 = time.perf_counter()
  jitted = fusion.fuse_frame_donating
  compiled = jitted.lower(state, dev_frames[0], frames.camera, rule).compile()
  compile_s = time.perf_counter() - t0
  fn = jf.fuse_frame if public else fusion.fuse_frame_donating
  fuser = _Fuser(state, dev_frames, frames.camera, rule, fn)
  seconds = median_time(fuser, repeats)
  core_seconds = None
  if public:
    fuser.fn = fusion.fuse_frame_donating
    core_seconds = median_time(fuser, repeats)
  points = float(np.mean(np.sum(frames.depth > 0, axis=(1, 2))))
  return {
      "rule": rule_name, "height": height, "width": width, "num_classes": k,
      "capacity": capacity, "compile_s": compile_s, "ms_per_frame": 1e3 * seconds,
      "frames_per_s": 1.0 / seconds, "points_per_s": points / seconds,
      "core_ms_per_frame": None if core_seconds is None else 1e3 * core_seconds,
      "core_frames_per_s": None if core_seconds is None else 1.0 / core_seconds,
      "occupied": int(fuser.state.num_occupied), "memory": _memory(compiled),
  }


def numpy_row(frames, rule_name, *, repeats, voxel_size, capacity=2**20) -> dict:
  """Per-frame time of the vectorised NumPy peer on the same frames (map kept across frames),
  interleaved call by call with the jitted step of `fuse_frame` on the same frames, so that
  both see the same machine load (the machine may be shared); `speedup` is the ratio of the
  medians."""
  k = frames.probs.shape[-1]
  peer = numpy_peer.NumpyMap(k, rule_name, voxel_size=voxel_size)
  rule = jf.rules.by_name(rule_name)
  fuser = _Fuser(jf.init_map(capacity=capacity, num_classes=k, voxel_size=voxel_size,
                             rule=rule), _device_frames(frames), frames.camera, rule,
                 fusion.fuse_frame_donating)
  t = [0]

  def step():
    i = t[0] % frames.depth.shape[0]
    peer.fuse(frames.depth[i], frames.poses[i], frames.probs[i], frames.var[i], frames.camera)
    t[0] += 1

  step()
  jax.block_until_ready(fuser())
  ours, theirs = [], []
  for _ in range(repeats):
    t0 = time.perf_counter()
    step()
    theirs.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    jax.block_until_ready(fuser())
    ours.append(time.perf_counter() - t0)
  seconds, core = float(np.median(theirs)), float(np.median(ours))
  return {"rule": rule_name, "ms_per_frame": 1e3 * seconds, "frames_per_s": 1.0 / seconds,
          "core_ms_interleaved": 1e3 * core, "speedup": seconds / core}


def _filled_state(capacity, fill, num_classes, rule, voxel_size, seed=0):
  """A map whose hash table holds `fill · capacity` random far-away voxels."""
  state = jf.init_map(capacity=capacity, num_classes=num_classes, voxel_size=voxel_size,
                      rule=rule)
  count = int(fill * capacity)
  if count == 0:
    return state
  rng = np.random.default_rng(seed)
  keys = rng.integers(-10**6, 10**6, (count, 3)).astype(np.int32)
  keys[:, 2] = 10**6 + np.arange(count)        # distinct, and far from the room
  insert = jax.jit(lambda t, c, k, a: hashing.insert(t, c, k, a, max_probes=capacity))
  table, claims = state.keys, state.claims
  chunk = 2**16
  for start in range(0, count, chunk):
    part = keys[start:start + chunk]
    active = np.arange(chunk) < len(part)
    part = np.concatenate([part, np.zeros((chunk - len(part), 3), np.int32)])
    res = insert(table, claims, jnp.asarray(part), jnp.asarray(active))
    table, claims = res.table, res.claims
  occupied = int(jnp.sum(table[:, 0] != hashing.EMPTY))
  return state.replace(keys=table, claims=claims, num_occupied=jnp.asarray(occupied, jnp.int32))


def capacity_rows(frames, config) -> list:
  rows = []
  rule = jf.rules.by_name(HEADLINE["rule"])
  k = frames.probs.shape[-1]
  dev_frames = _device_frames(frames)
  for capacity in config.capacities:
    for fill in config.fills:
      state = _filled_state(capacity, fill, k, rule, config.voxel_size)
      fuser = _Fuser(state, dev_frames, frames.camera, rule,
                     fusion.fuse_frame_donating)
      seconds = median_time(fuser, config.repeats)
      rows.append({"capacity": capacity, "fill": fill,
                   "load_after": int(fuser.state.num_occupied) / capacity,
                   "dropped": int(fuser.state.num_dropped), "ms_per_frame": 1e3 * seconds})
      del fuser, state
  return rows


def pixel_rows(config) -> list:
  rows = []
  for height, width in config.pixel_scaling:
    frames = scene.make_frames(config.num_frames, height=height, width=width,
                               num_classes=HEADLINE["num_classes"], seed=3)
    row = fuse_frame_row(frames, HEADLINE["rule"], capacity=config.capacity,
                         repeats=config.repeats, voxel_size=config.voxel_size, public=False)
    row["pixels"] = height * width
    rows.append(row)
  return rows


def sequence_row(frames, config) -> dict:
  rule = jf.rules.by_name(HEADLINE["rule"])
  k = frames.probs.shape[-1]
  stacked = jax.device_put(frames.stacked())
  holder = {"state": jf.init_map(capacity=config.capacity, num_classes=k,
                                 voxel_size=config.voxel_size, rule=rule)}

  def step():
    holder["state"] = fusion.fuse_sequence_donating(
        holder["state"], stacked, frames.camera, rule)
    return holder["state"]

  t0 = time.perf_counter()
  jax.block_until_ready(step())
  first = time.perf_counter() - t0
  seconds = median_time(step, max(2, config.repeats // 3))
  length = frames.depth.shape[0]
  return {"frames": length, "first_call_s": first, "ms_per_frame": 1e3 * seconds / length,
          "frames_per_s": length / seconds}


def floor_row(frames, *, repeats, core_ms=None) -> dict:
  """The floor of a D+R frame: one fused pass that reads depth, probabilities and variances,
  computes D+R's per-pixel terms (`rule.observe`, the engine's own kernel) and reduces them,
  with no grouping, hashing or scatter. Two forms, the faster is the floor: the terms written
  out, and the terms reduced per pixel over K and summed over the pixels in 10 blocks. (Reducing
  them over the pixels to per-class sums, a column reduction, is 3× slower on XLA-CPU.)"""
  rule = jf.rules.by_name("robust_dr")
  n = frames.depth.shape[1] * frames.depth.shape[2]
  k = frames.probs.shape[-1]
  depth, probs, var = (jax.device_put(x[0].reshape(n, -1)) for x in
                       (frames.depth, frames.probs, frames.var))

  def terms(p, v):
    t = jax.vmap(rule.observe, in_axes=(0, 0, None))(p, v, rule.hparams)
    return t.sums["wloglik"], t.maxes["neg_shifted_var"]

  def written(d, p, v):
    w, m = terms(p, v)
    return jnp.where(d > 0, w, 0.0), m

  def reduced(d, p, v, blocks=10):
    size = n // blocks

    def body(b, acc):
      pb, vb = (jax.lax.dynamic_slice(x, (b * size, 0), (size, k)) for x in (p, v))
      db = jax.lax.dynamic_slice(d, (b * size, 0), (size, 1))[:, 0]
      w, m = terms(pb, vb)
      return acc + jnp.sum(jnp.where(db > 0, jnp.sum(w, -1) + jnp.max(m, -1), 0.0))

    return jax.lax.fori_loop(0, blocks, body, jnp.zeros((), jnp.float32))

  forms = {}
  for name, fn in (("terms written", written), ("terms reduced", reduced)):
    jitted = jax.jit(fn)
    forms[name] = 1e3 * median_time(lambda f=jitted: f(depth, probs, var), repeats)
  floor_ms = min(forms.values())
  return {"forms_ms": forms, "floor_ms": floor_ms, "dr_core_ms": core_ms,
          "dr_over_floor": None if core_ms is None else core_ms / floor_ms}


def aligned_row(config, height, width, k) -> dict:
  """D+R on the same room with its surfaces on voxel faces (`scene.make_frames(aligned=True)`):
  with depth noise each such surface splits across two voxel layers, a stress case."""
  frames = scene.make_frames(config.num_frames, height=height, width=width, num_classes=k,
                             aligned=True)
  return fuse_frame_row(frames, HEADLINE["rule"], capacity=config.capacity,
                        repeats=config.repeats, voxel_size=config.voxel_size)


def loop_rows(frames, config, *, sequence_core_ms_per_frame: float) -> dict:
  """Per-frame cost of one sequence fused three ways, D+R, each into a map of its own that is
  kept (donated) from call to call: a Python loop of the public `fuse_frame` and one public
  `fuse_sequence` (a scan; it checks every value, `fuse_frame` a sample), beside its jitted core
  `fuse_sequence_donating` alone, timed on the same frames by `sequence_row` (passed in).
  `fuse_batch` (the scan under `vmap`, B = 1) returns new maps, so it is timed from an empty map
  each call, beside the `init_map` it includes."""
  rule = jf.rules.by_name(HEADLINE["rule"])
  k = frames.probs.shape[-1]
  length = frames.depth.shape[0]
  dev = _device_frames(frames)
  stacked = jax.device_put(frames.stacked())
  batched = jax.device_put(jax.tree.map(lambda x: x[None], frames.stacked()))
  fresh = lambda: jf.init_map(capacity=config.capacity, num_classes=k,
                              voxel_size=config.voxel_size, rule=rule)
  holder = {}

  def loop():
    state = holder["loop"]
    for frame in dev:
      state = jf.fuse_frame(state, frame, frames.camera, rule)
    holder["loop"] = state
    return state

  def sequence():
    holder["sequence"] = jf.fuse_sequence(holder["sequence"], stacked, frames.camera, rule)
    return holder["sequence"]

  def batch():
    return jf.fuse_batch(batched, frames.camera, rule, capacity=config.capacity,
                         voxel_size=config.voxel_size)

  repeats = max(3, config.repeats // 3)
  rows = {"frames": length, "init_map_ms": 1e3 * median_time(fresh, repeats)}
  rows["sequence_core_ms_per_frame"] = sequence_core_ms_per_frame
  for name, fn in (("loop", loop), ("sequence", sequence), ("batch", batch)):
    holder[name] = fresh()
    rows[f"{name}_ms_per_frame"] = 1e3 * median_time(fn, repeats) / length
    holder.pop(name)
  return rows


def sampler_rows(config, *, model=None) -> list:
  """The shipped net's MC sampler (`models.sampling.mc_samples`: the layers before the first
  dropout once per image, the rest vmapped over M keys) against every sample a full pass of
  its own (the image broadcast to M, then the same vmap): the same samples up to rounding."""
  import functools  # pylint: disable=import-outside-toplevel
  from models import checkpoint  # pylint: disable=import-outside-toplevel
  from models import net  # pylint: disable=import-outside-toplevel
  from models import sampling  # pylint: disable=import-outside-toplevel
  model = checkpoint.load_pretrained() if model is None else model

  @functools.partial(jax.jit, static_argnums=0, static_argnames="num_samples")
  def unshared(graphdef, params, key, image, *, num_samples):
    images = jnp.broadcast_to(image, (num_samples,) + image.shape)
    return jax.vmap(lambda k_, im: jax.nn.softmax(
        net.apply(graphdef, params, k_, im[None], deterministic=False)[0], axis=-1))(
            jax.random.split(key, num_samples), images)

  rows = []
  for (height, width), m in config.sampler:
    image = np.random.default_rng(0).integers(0, 256, (height, width, 3), dtype=np.uint8)
    key = jax.random.key(1)
    repeats = max(2, config.pipeline_repeats)
    shared_s = median_time(lambda: sampling.mc_samples(model.graphdef, model.params, key, image,
                                                       num_samples=m), repeats)
    prepared = sampling.prepare_images(image)
    full_s = median_time(lambda: unshared(model.graphdef, model.params, key, prepared,
                                          num_samples=m), repeats)
    rows.append({"height": height, "width": width, "M": m, "shared_ms": 1e3 * shared_s,
                 "full_passes_ms": 1e3 * full_s, "speedup": full_s / shared_s})
  return rows


def mc_rows(config, height, width) -> list:
  """`mc_moments` of an `(M, H, W, K)` stack against NumPy's `samples.sum(0)` of the same stack
  (one read of the samples: the floor of any moment computation), interleaved in this process.

  `ms_per_frame` is the plain call as the README writes it (`mean, var = jf.mc_moments(samples)`,
  on a device array), `jit_ms_per_frame` the same call inside the caller's `jax.jit`.
  """
  rows = []
  k = HEADLINE["num_classes"]
  rng = np.random.default_rng(0)
  jitted = jax.jit(jf.mc_moments)
  for m in config.mc_samples:
    logits = rng.normal(size=(m, height, width, k)).astype(np.float32)
    host = np.exp(logits - logits.max(-1, keepdims=True))
    host /= host.sum(-1, keepdims=True)
    del logits
    samples = jax.device_put(host)
    jax.block_until_ready(jf.mc_moments(samples))
    jax.block_until_ready(jitted(samples))
    ours, inside, peer = [], [], []
    for _ in range(config.repeats):
      t0 = time.perf_counter()
      jax.block_until_ready(jf.mc_moments(samples))
      ours.append(time.perf_counter() - t0)
      t0 = time.perf_counter()
      jax.block_until_ready(jitted(samples))
      inside.append(time.perf_counter() - t0)
      t0 = time.perf_counter()
      host.sum(0)
      peer.append(time.perf_counter() - t0)
    rows.append({"M": m, "height": height, "width": width, "num_classes": k,
                 "ms_per_frame": 1e3 * float(np.median(ours)),
                 "jit_ms_per_frame": 1e3 * float(np.median(inside)),
                 "numpy_sum0_ms": 1e3 * float(np.median(peer))})
    del samples, host
  return rows


def pipeline_rows(config, *, model=None) -> list:
  """A user's frames end to end: the shipped network's MC samples (`models.sampling`, M dropout
  keys, B frames in one vmapped call) → `mc_moments` (vmapped over the B frames) → `fuse_frame`
  of each frame (D+R), on rendered room frames with random RGB. Each of `pipeline_repeats` runs
  (after one warm-up run that compiles) times the three stages in a row, each ended by
  `block_until_ready`; the table gives their medians."""
  from models import checkpoint  # pylint: disable=import-outside-toplevel
  from models import sampling  # pylint: disable=import-outside-toplevel
  model = checkpoint.load_pretrained() if model is None else model
  k = model.config.num_classes
  moments = jax.jit(jax.vmap(jf.mc_moments))
  rule = jf.rules.by_name(HEADLINE["rule"])
  rows = []
  for (height, width), m, b in config.pipeline:
    frames = scene.make_frames(b, height=height, width=width, num_classes=max(k, 7), seed=11)
    images = np.random.default_rng(0).integers(0, 256, (b, height, width, 3), dtype=np.uint8)
    state = jf.init_map(capacity=config.capacity, num_classes=k, voxel_size=config.voxel_size,
                        rule=rule)
    times = []
    for run_index in range(config.pipeline_repeats + 1):
      t0 = time.perf_counter()
      samples = jax.block_until_ready(sampling.mc_samples_batch(
          model.graphdef, model.params, jax.random.key(run_index), images, num_samples=m))
      t1 = time.perf_counter()
      mean, var = jax.block_until_ready(moments(samples))
      t2 = time.perf_counter()
      for i in range(b):
        state = jf.fuse_frame(state, jf.Frame(frames.depth[i], frames.poses[i], mean[i], var[i]),
                              frames.camera, rule)
      jax.block_until_ready(state)
      t3 = time.perf_counter()
      if run_index:                     # run 0 compiles
        times.append((t1 - t0, t2 - t1, t3 - t2))
      del samples, mean, var
    sample_s, moments_s, fuse_s = (float(np.median(t)) for t in zip(*times))
    total_s = sample_s + moments_s + fuse_s
    rows.append({
        "height": height, "width": width, "M": m, "frames_per_call": b, "num_classes": k,
        "sample_ms_per_frame": 1e3 * sample_s / b, "moments_ms_per_frame": 1e3 * moments_s / b,
        "fuse_ms_per_frame": 1e3 * fuse_s / b, "end_to_end_ms_per_frame": 1e3 * total_s / b,
        "frames_per_s": b / total_s, "sample_share": sample_s / total_s,
        "moments_share": moments_s / total_s, "fuse_share": fuse_s / total_s})
    del state
  return rows


def run(config: Config, *, out_dir, log=print) -> dict:
  """Runs every measurement of `config` and writes results.json / results.md to `out_dir`."""
  out_dir = pathlib.Path(out_dir)
  out_dir.mkdir(parents=True, exist_ok=True)
  results = {"machine": machine(), "device": jax.devices()[0].device_kind,
             "config": dataclasses.asdict(config), "throughput": [], "numpy_peer": [],
             "open3d_peer": None}
  headline_frames, peer_frames = None, {}
  for height, width in config.resolutions:
    for k in config.classes:
      frames = scene.make_frames(config.num_frames, height=height, width=width, num_classes=k)
      for rule_name in config.rules:
        row = fuse_frame_row(frames, rule_name, capacity=config.capacity,
                             repeats=config.repeats, voxel_size=config.voxel_size)
        results["throughput"].append(row)
        log(f"fuse_frame {rule_name:10s} {height}x{width} K={k}: {row['ms_per_frame']:.2f} ms "
            f"({row['frames_per_s']:.1f} frames/s; core {row['core_ms_per_frame']:.2f} ms), "
            f"compile {row['compile_s']:.2f} s")
      # The peers run at the largest resolution, for every K; the capacity scan and the other
      # stages use K = 13 there (or the last K).
      if (height, width) == config.resolutions[-1]:
        peer_frames[k] = frames
        if k == HEADLINE["num_classes"] or headline_frames is None:
          headline_frames = frames
  # Peers on the same frames, one after the other, in this process.
  for k, frames in peer_frames.items():
    for rule_name in config.rules:
      row = numpy_row(frames, rule_name, repeats=config.peer_repeats,
                      voxel_size=config.voxel_size, capacity=config.capacity)
      row["num_classes"] = k
      results["numpy_peer"].append(row)
      log(f"numpy peer {rule_name:10s} K={k}: {row['ms_per_frame']:.1f} ms, interleaved with "
          f"ours {row['core_ms_interleaved']:.1f} ms: {row['speedup']:.1f}x")
  results["open3d_peer"] = open3d_peer.measure(headline_frames, voxel_size=config.voxel_size,
                                               repeats=config.peer_repeats)
  log(f"open3d peer: {results['open3d_peer']}")
  results["headline_shape"] = list(headline_frames.probs.shape[1:])
  results["pixels"] = pixel_rows(config)
  log("pixel scaling: " + ", ".join(f"{r['pixels']}: {r['ms_per_frame']:.2f} ms"
                                    for r in results["pixels"]))
  results["capacity"] = capacity_rows(headline_frames, config)
  log("capacity scaling: " + ", ".join(
      f"2^{int(np.log2(r['capacity']))}@{r['fill']:.2f}: {r['ms_per_frame']:.2f} ms"
      for r in results["capacity"]))
  seq_frames = scene.make_frames(config.sequence_length, height=headline_frames.depth.shape[1],
                                 width=headline_frames.depth.shape[2],
                                 num_classes=headline_frames.probs.shape[-1], seed=5)
  results["sequence"] = sequence_row(seq_frames, config)
  log(f"fuse_sequence: {results['sequence']}")
  results["loops"] = loop_rows(seq_frames, config, sequence_core_ms_per_frame=results[
      "sequence"]["ms_per_frame"])
  log(f"loop / fuse_sequence / fuse_batch: {results['loops']}")
  h_w_k = (headline_frames.depth.shape[1], headline_frames.depth.shape[2],
           headline_frames.probs.shape[-1])
  headline_core = next((r["core_ms_per_frame"] for r in results["throughput"]
                        if r["rule"] == "robust_dr" and
                        (r["height"], r["width"], r["num_classes"]) == h_w_k), None)
  results["floor"] = floor_row(headline_frames, repeats=config.repeats, core_ms=headline_core)
  log(f"floor: {results['floor']}")
  results["aligned"] = aligned_row(config, *h_w_k)
  log(f"aligned room, D+R: {results['aligned']['ms_per_frame']:.2f} ms "
      f"({results['aligned']['occupied']} voxels)")
  results["sampler"] = sampler_rows(config)
  log(f"sampler: {results['sampler']}")
  results["mc_moments"] = mc_rows(config, *headline_frames.depth.shape[1:])
  log(f"mc_moments: {results['mc_moments']}")
  results["pipeline"] = pipeline_rows(config)
  for r in results["pipeline"]:
    log(f"pipeline {r['height']}x{r['width']} M={r['M']}: {r['end_to_end_ms_per_frame']:.1f} "
        f"ms/frame (sample {r['sample_share']:.0%}, moments {r['moments_share']:.0%}, "
        f"fuse {r['fuse_share']:.0%})")
  results["max_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
  (out_dir / "results.json").write_text(json.dumps(results, indent=1))
  (out_dir / "results.md").write_text(to_markdown(results))
  try:
    plot(results, out_dir / "scaling.png")
  except ImportError:
    pass
  return results


def _fmt(x) -> str:
  return "—" if x is None else f"{x:.2f}"


def config_frames(results: dict) -> int:
  return results["config"]["num_frames"]


def _headline_occupied(results: dict) -> str:
  h, w, k = results["headline_shape"]
  for r in results["throughput"]:
    if (r["rule"], r["height"], r["width"], r["num_classes"]) == (HEADLINE["rule"], h, w, k):
      return f"{r['occupied']} voxels"
  return "—"


def _ratio(a, b):
  return f"{a / b:.1f}×" if a and b else "—"


def to_markdown(results: dict) -> str:
  """The tables of RESULTS.md from a results dict."""
  m = results["machine"]
  lines = [f"Device: **{m['device_kind']}** ({m['platform']}), {m['cpu_count']} CPUs "
           f"({m['cpu']}), load average {m['load_avg_1_5_15']}, jax {m['jax']}, {m['time']}.", ""]
  lines += ["### fuse_frame throughput (median per frame; `public` includes the host-side input "
            "checks of `fuse_frame`, `core` is the jitted step alone)", "",
            "| rule | H×W | K | compile s | public ms | public frames/s | core ms | core frames/s "
            "| Mpoints/s | XLA peak MB |",
            "|---|---|---|---|---|---|---|---|---|---|"]
  for r in results["throughput"]:
    peak = r["memory"]["peak_mb"] if r.get("memory") else float("nan")
    lines.append(f"| {r['rule']} | {r['height']}×{r['width']} | {r['num_classes']} | "
                 f"{r['compile_s']:.2f} | {r['ms_per_frame']:.2f} | {r['frames_per_s']:.1f} | "
                 f"{r['core_ms_per_frame']:.2f} | {r['core_frames_per_s']:.1f} | "
                 f"{r['points_per_s'] / 1e6:.1f} | {peak:.0f} |")
  h, w, k = results["headline_shape"]
  lines += ["", f"### Peers on the same {h}×{w} frames, same process (NumPy peer and our jitted "
            "step called alternately, so both see the same load)", "",
            "| rule | K | jaxfusion core ms (interleaved) | NumPy peer ms | speed-up vs NumPy "
            "(target ≥ 5×) |", "|---|---|---|---|---|"]
  core = {r["rule"]: r["core_ms_per_frame"] for r in results["throughput"]
          if (r["height"], r["width"], r["num_classes"]) == (h, w, k)}
  for r in results["numpy_peer"]:
    c = r.get("core_ms_interleaved", core.get(r["rule"]))
    lines.append(f"| {r['rule']} | {r.get('num_classes', k)} | {c:.2f} | "
                 f"{r['ms_per_frame']:.1f} | {_ratio(r['ms_per_frame'], c)} |")
  o3d = results["open3d_peer"]
  if o3d and o3d.get("ms_per_frame"):
    c = core.get(HEADLINE["rule"])
    lines += ["", f"Open3D {o3d['version']} `{o3d['method']}` (CPU, TSDF, voxel "
              f"{o3d['voxel_size']} m, {o3d['detail']}): **{o3d['ms_per_frame']:.2f} ms** per "
              f"frame; jaxfusion D+R core / Open3D = {c / o3d['ms_per_frame']:.2f}."]
  else:
    lines += ["", f"Open3D: {o3d.get('status') if o3d else 'not measured'}."]
  lines += ["", "### Cost against pixels per frame (D+R, K = 13, core)", "",
            "| pixels | ms | ns / pixel |", "|---|---|---|"]
  for r in results["pixels"]:
    lines.append(f"| {r['pixels']} | {r['ms_per_frame']:.2f} | "
                 f"{1e6 * r['ms_per_frame'] / r['pixels']:.1f} |")
  lines += ["", "### Cost against map capacity and fill (D+R, headline frames, core)", "",
            "| capacity | fill before | load after | ms |", "|---|---|---|---|"]
  for r in results["capacity"]:
    lines.append(f"| 2^{int(np.log2(r['capacity']))} | {r['fill']:.2f} | "
                 f"{r['load_after']:.3f} | {r['ms_per_frame']:.2f} |")
  s = results["sequence"]
  lines += ["", f"### fuse_sequence (scan of {s['frames']} frames, D+R): "
            f"{s['ms_per_frame']:.2f} ms per frame ({s['frames_per_s']:.1f} frames/s; first call "
            f"incl. compile {s['first_call_s']:.1f} s)", "",
            "### One sequence four ways (D+R; ms per frame; `fuse_batch` from an empty map each "
            "call, its `init_map` included)", "",
            "| frames | loop of fuse_frame | fuse_sequence | fuse_sequence core | fuse_batch "
            "(B = 1) | init_map ms |", "|---|---|---|---|---|---|",
            f"| {results['loops']['frames']} | {results['loops']['loop_ms_per_frame']:.2f} | "
            f"{results['loops']['sequence_ms_per_frame']:.2f} | "
            f"{results['loops']['sequence_core_ms_per_frame']:.2f} | "
            f"{results['loops']['batch_ms_per_frame']:.2f} | "
            f"{results['loops']['init_map_ms']:.2f} |", "",
            "### The floor of a D+R frame (one fused pass: read, per-pixel terms, reduce)", "",
            "| form | ms |", "|---|---|"] + [
            f"| {name} | {ms:.2f} |" for name, ms in results["floor"]["forms_ms"].items()] + [
            "", f"D+R core {_fmt(results['floor']['dr_core_ms'])} ms = "
            f"**{_fmt(results['floor']['dr_over_floor'])}× the floor** (target ≤ 2.5×).", "",
            f"Aligned room (surfaces on voxel faces, a stress case), D+R: "
            f"{results['aligned']['ms_per_frame']:.2f} ms per frame (core "
            f"{results['aligned']['core_ms_per_frame']:.2f} ms), "
            f"{results['aligned']['occupied']} voxels after {config_frames(results)} frames "
            f"(off-grid: {_headline_occupied(results)}).", "",
            "### MC sampler: layers before the first dropout shared, against a full pass per "
            "sample", "", "| H×W | M | shared ms | full passes ms | speed-up |",
            "|---|---|---|---|---|"] + [
            f"| {r['height']}×{r['width']} | {r['M']} | {r['shared_ms']:.1f} | "
            f"{r['full_passes_ms']:.1f} | {r['speedup']:.2f}× |" for r in results["sampler"]] + [
            "",
            "### MC front end: `mc_moments` per frame, against NumPy's `samples.sum(0)` of the "
            "same stack (interleaved, same process)", "",
            "| M | mc_moments ms (plain call) | inside jax.jit ms | NumPy sum(0) ms | ratio, "
            "plain (target ≤ 2) |", "|---|---|---|---|---|"]
  for r in results["mc_moments"]:
    lines.append(f"| {r['M']} | {r['ms_per_frame']:.2f} | {r['jit_ms_per_frame']:.2f} | "
                 f"{r['numpy_sum0_ms']:.2f} | {r['ms_per_frame'] / r['numpy_sum0_ms']:.2f} |")
  lines += ["", "### The whole pipeline per frame: shipped network's MC samples (B frames per "
            "vmapped call) → `mc_moments` → `fuse_frame` (D+R)", "",
            "| H×W | M | B | K | sample ms | moments ms | fuse ms | end to end ms | frames/s "
            "| share sample / moments / fuse |", "|---|---|---|---|---|---|---|---|---|---|"]
  for r in results.get("pipeline", []):
    lines.append(
        f"| {r['height']}×{r['width']} | {r['M']} | {r['frames_per_call']} | "
        f"{r['num_classes']} | {r['sample_ms_per_frame']:.1f} | {r['moments_ms_per_frame']:.1f}"
        f" | {r['fuse_ms_per_frame']:.1f} | {r['end_to_end_ms_per_frame']:.1f} | "
        f"{r['frames_per_s']:.2f} | {r['sample_share']:.0%} / {r['moments_share']:.0%} / "
        f"{r['fuse_share']:.0%} |")
  lines += ["", f"Process peak RSS: {results['max_rss_mb']:.0f} MB.", ""]
  return "\n".join(lines)


def plot(results: dict, path) -> None:
  """Two panels: ms against pixels (linear?) and against capacity per fill (flat?)."""
  import matplotlib  # pylint: disable=import-outside-toplevel
  matplotlib.use("Agg")
  import matplotlib.pyplot as plt  # pylint: disable=import-outside-toplevel
  fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
  px = [r["pixels"] for r in results["pixels"]]
  ms = [r["ms_per_frame"] for r in results["pixels"]]
  a.plot(px, ms, "o-", label="D+R, K=13")
  if px:
    a.plot(px, [ms[-1] * p / px[-1] for p in px], "--", color="gray", label="linear")
  a.set_xlabel("pixels per frame")
  a.set_ylabel("ms per frame")
  a.set_xscale("log")
  a.set_yscale("log")
  a.legend()
  a.set_title("cost vs pixels")
  for fill in sorted({r["fill"] for r in results["capacity"]}):
    rows = [r for r in results["capacity"] if r["fill"] == fill]
    b.plot([r["capacity"] for r in rows], [r["ms_per_frame"] for r in rows], "o-",
           label=f"fill {fill:.2f}")
  b.set_xscale("log", base=2)
  b.set_ylim(bottom=0)
  b.set_xlabel("map capacity (slots)")
  b.set_ylabel("ms per frame")
  b.set_title("cost vs capacity and fill")
  b.legend()
  fig.suptitle(f"jaxfusion fuse_frame on {results['device']}")
  fig.tight_layout()
  fig.savefig(path, dpi=100)
  plt.close(fig)
