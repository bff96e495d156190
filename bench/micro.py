"""`python -m bench.micro [terms|moments|outer-jit]`: the A/B micro-benchmarks quoted in RESULTS.md.

* `terms`: D+R's per-pixel terms (two logarithms per class) of a 640×480, K = 13 frame, reduced
  (a) over 10 dynamically sliced blocks in a `fori_loop` as `fuse_frame` does, (b) in one fused
  pass over the whole frame — each without and with the scatter-add / scatter-max into 8 193
  per-voxel rows.
* `moments`: forms of the MC moments of a (32, 480, 640, 13) stack against NumPy's
  `samples.sum(0)`: `jaxfusion.mc_moments` (fused groups of 32), groups of 8 in a `fori_loop`, a
  `fori_loop` over single samples, and the old two-pass `jnp.mean` form.
* `outer-jit`: a user's Python loop of `jf.fuse_frame` over 4 frames (640×480, K = 13, D+R) inside
  one `jax.jit` that donates the map at the top, against the same loop of the donating step;
  per frame (divide by 4), plus the outer program's XLA buffer sizes (an aliased map is not
  copied per frame).

Every variant is called in turn, repeatedly, in one process, so all see the same machine load;
the tables give min and median ms.
"""

import argparse
import functools
import os
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

import jaxfusion as jf


def _interleaved(fns: dict, args, repeats: int) -> dict:
  for f in fns.values():
    jax.block_until_ready(f(*args))
  times = {k: [] for k in fns}
  for _ in range(repeats):
    for k, f in fns.items():
      t0 = time.perf_counter()
      jax.block_until_ready(f(*args))
      times[k].append(time.perf_counter() - t0)
  return {k: (1e3 * min(v), 1e3 * float(np.median(v))) for k, v in times.items()}


def terms(repeats: int = 15, num_pixels: int = 480 * 640, num_classes: int = 13,
          blocks: int = 10) -> dict:
  """min / median ms of the D+R per-pixel terms, blocked in a loop vs whole, ± scatters."""
  size = num_pixels // blocks
  k = num_classes
  rng = np.random.default_rng(0)
  p = jnp.asarray(rng.dirichlet(np.ones(k), num_pixels).astype(np.float32))
  v = jnp.asarray(rng.uniform(0, 0.1, (num_pixels, k)).astype(np.float32))
  seg = jnp.asarray(rng.integers(0, 5000, num_pixels).astype(np.int32))

  def dr_terms(pb, vb):
    alpha = -jnp.log(jnp.clip(jnp.where(jnp.isfinite(vb), vb, 0.0), 0.0, 0.25) + 1e-12)
    pb = jnp.where(jnp.isfinite(pb), jnp.maximum(pb, 0.0), 1.0 / k)
    log_p = jnp.log(jnp.maximum(0.7 * pb + 0.3 / k, np.float32(1.17549435e-38)))
    return alpha * log_p, alpha

  def init(scatter):
    if scatter:
      return jnp.zeros((8193, k)), jnp.full((8193, k), -jnp.inf)
    return jnp.zeros(k), jnp.zeros(k)

  def blocked(p, v, seg, scatter):
    def body(b, acc):
      s, m = dr_terms(lax.dynamic_slice(p, (b * size, 0), (size, k)),
                      lax.dynamic_slice(v, (b * size, 0), (size, k)))
      if scatter:
        sb = lax.dynamic_slice(seg, (b * size,), (size,))
        return acc[0].at[sb].add(s), acc[1].at[sb].max(m)
      return acc[0] + s.sum(0), acc[1] + m.max(0)
    return lax.fori_loop(0, blocks, body, init(scatter))

  def whole(p, v, seg, scatter):
    s, m = dr_terms(p, v)
    if scatter:
      zero_s, zero_m = init(True)
      return zero_s.at[seg].add(s), zero_m.at[seg].max(m)
    return s.sum(0), m.max(0)

  fns = {}
  for scatter in (False, True):
    fns[f"blocked loop, scatter={scatter}"] = jax.jit(functools.partial(blocked, scatter=scatter))
    fns[f"whole frame, scatter={scatter}"] = jax.jit(functools.partial(whole, scatter=scatter))
  return _interleaved(fns, (p, v, seg), repeats)


def moments(repeats: int = 7, num_samples: int = 32, height: int = 480, width: int = 640,
            num_classes: int = 13) -> dict:
  """min / median ms of MC-moment forms and of NumPy's `samples.sum(0)`, same stack (the loop
  forms read `M // group` whole groups: use an M divisible by 8)."""
  x = np.random.default_rng(0).dirichlet(np.ones(num_classes), (num_samples, height, width))
  x = x.astype(np.float32)
  xj = jnp.asarray(x)

  def shifted_fori(s, group):
    m, first = s.shape[0], s[0]

    def body(i, acc):
      d = lax.dynamic_slice_in_dim(s, i * group, group) - first
      s1, s2 = acc
      for j in range(group):        # explicit adds: XLA CPU reduces a leading axis slowly
        s1, s2 = s1 + d[j], s2 + d[j] * d[j]
      return s1, s2

    zero = jnp.zeros_like(first)
    s1, s2 = lax.fori_loop(0, m // group, body, (zero, zero))
    mean_d = s1 / m
    return first + mean_d, jnp.maximum(s2 / m - mean_d * mean_d, 0.0)

  def two_pass(s):
    mean = jnp.mean(s, 0)
    return mean, jnp.mean(jnp.square(s - mean[None]), 0)

  fns = {"numpy samples.sum(0)": lambda a: x.sum(0),
         "mc_moments (fused groups of 32)": jax.jit(jf.mc_moments),
         "fori_loop, groups of 8": jax.jit(lambda s: shifted_fori(s, min(8, num_samples))),
         "fori_loop, single samples": jax.jit(lambda s: shifted_fori(s, 1)),
         "old two-pass jnp.mean": jax.jit(two_pass)}
  return _interleaved(fns, (xj,), repeats)


def outer_jit(repeats: int = 7, num_frames: int = 4, height: int = 480, width: int = 640,
              capacity: int = 2**20) -> dict:
  from bench import scene  # pylint: disable=import-outside-toplevel
  from jaxfusion import fusion  # pylint: disable=import-outside-toplevel
  frames = scene.make_frames(num_frames, height=height, width=width, num_classes=13, seed=5)
  rule = jf.rules.by_name("robust_dr")
  camera = frames.camera
  dev = [jax.device_put(frames.frame(t)) for t in range(num_frames)]

  @functools.partial(jax.jit, donate_argnums=0)
  def user_loop(state, frame_list):
    for frame in frame_list:      # traced inline: the non-donating step, planned as one program
      state = jf.fuse_frame(state, frame, camera, rule)
    return state

  fresh = lambda: jf.init_map(capacity=capacity, num_classes=13, rule=rule)
  held = {"outer": fresh(), "steps": fresh()}
  memory = user_loop.lower(held["outer"], dev).compile().memory_analysis()
  print(f"outer jit: arguments {memory.argument_size_in_bytes / 2**20:.0f} MB, aliased "
        f"{memory.alias_size_in_bytes / 2**20:.0f} MB, temp {memory.temp_size_in_bytes / 2**20:.0f}"
        " MB")

  def outer(_):
    held["outer"] = user_loop(held["outer"], dev)
    return held["outer"]

  def steps(_):
    state = held["steps"]
    for frame in dev:
      state = fusion.fuse_frame_donating(state, frame, camera, rule)
    held["steps"] = state
    return state

  return _interleaved({f"loop of the donating step ({num_frames} frames)": steps,
                       f"user loop under one outer jit ({num_frames} frames)": outer}, (None,),
                      repeats)


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(prog="python -m bench.micro",
                                   description=__doc__.split("\n")[0])
  parser.add_argument("which", nargs="*", default=["terms", "moments"],
                      choices=["terms", "moments", "outer-jit"])
  parser.add_argument("--repeats", type=int, default=None)
  args = parser.parse_args(argv)
  for name in args.which:
    fn = {"terms": terms, "moments": moments, "outer-jit": outer_jit}[name]
    results = fn() if args.repeats is None else fn(repeats=args.repeats)
    print(f"\n{name} (load average {os.getloadavg()}):")
    base = next(iter(results.values()))[0]
    for k, (lo, med) in results.items():
      print(f"  {k:36s} min {lo:8.1f} ms   median {med:8.1f} ms   min / first {lo / base:5.2f}")


if __name__ == "__main__":
  main()
