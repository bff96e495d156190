"""`python -m bench.growth [--quick]`: what a growing map costs over a long walk.

A camera walks 2,000 frames down a 60 m corridor (2.4 m wide, 2.7 m high, rough walls; 120×160
depth, K = 13, D+R) into a `Mapper` with a 5 cm geometry layer, both starting small (2^14 slots,
2^10 blocks), so each layer grows several times. Each configuration of the `Mapper` (growth
factor 2, 4 or 8) runs the same frames in a fresh process of its own (its programs compiled
by itself), timed frame by frame, in turns of 50 frames with the same frames fused into a map
allocated at the final capacities from the start (compiled first; the capacities from a pilot
run in a process of its own): the flat baseline, under the same load of the machine. Reported:

* growth share: (time of the growing run − time of the fixed map) / time of the growing run,
  the first frame (the growing run's first compile) left out of both — everything growth
  costs;
* the frames that grew a layer: each one's time, and their excess over the median frame;
* the worst frame apart from the first (the longest stall) and the first frame.

Factor 4 also runs with a growth's rehash and compile one after the other, the `Mapper` before
12-08 (by default a worker thread rehashes while the grown half compiles); `--overlap-pairs N`
runs only those two, N times each in turns (`growth_overlap.json`).

The last configuration is a user's second run of the same walk with JAX's persistent
compilation cache on, as the `jaxfusion` commands turn it on (`jaxfusion.lab.compile_cache`):
a first run fills a fresh cache folder, the second is timed.

Writes `bench/results/growth.json` and prints a Markdown table. `--quick`: 300 frames at 60×80.
`--compiles`: only what a growth compiles, program by program (`compile_costs`;
`growth_compiles.json`). `--steady`: only a `Mapper` frame beside `fuse_frame` between growths,
in a plain loop and in one that waits for each frame (`steady_loops`; `growth_steady.json`);
with `--host-apart`, XLA's threads on a CPU of their own, as a host beside an accelerator
(`host_apart`; `growth_steady_apart.json`).
"""

import argparse
import json
import os
import pathlib
import subprocess
import sys
import tempfile
import time

import numpy as np

K = 13
TURN = 50      # frames the growing and the fixed map fuse in turn (`run_one`)
LENGTH, HALF_WIDTH, HEIGHT = 60.0, 1.2, 2.7
# (name, growth factor, persistent compilation cache warmed by a first run, the growth's
# compile and rehash overlapped: `jaxfusion.mapper._grown_while_compiling`)
CONFIGS = (("factor 2, compile on the frame that grows", 2, False, True),
           ("factor 4, compile on the frame that grows", 4, False, True),
           ("factor 4, rehash, then compile (not overlapped)", 4, False, False),
           ("factor 8, compile on the frame that grows", 8, False, True),
           ("factor 4, a repeat run with JAX's persistent compilation cache", 4, True, True))


def corridor_depth(T_world_cam: np.ndarray, camera, height: int, width: int) -> np.ndarray:
  """`(H, W) float32` z-depth of the corridor's rough walls, floor and ceiling from a pose."""
  v, u = np.mgrid[0:height, 0:width].astype(np.float64)
  rays = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u)],
                  -1) @ T_world_cam[:3, :3].T
  origin = T_world_cam[:3, 3]
  t = np.full((height, width), np.inf)
  for axis, lo, hi in ((0, -1.0, LENGTH + 1.0), (1, -HALF_WIDTH, HALF_WIDTH), (2, 0.0, HEIGHT)):
    with np.errstate(divide="ignore", invalid="ignore"):
      for bound in (lo, hi):
        hit = (bound - origin[axis]) / rays[..., axis]
        t = np.minimum(t, np.where(hit > 0, hit, np.inf))
  p = origin + t[..., None] * rays
  bump = (0.04 * np.sin(7.0 * p[..., 0]) * np.cos(5.0 * p[..., 2])
          + 0.03 * np.sin(13.0 * p[..., 1] + 3.0 * p[..., 0]))
  return (t + bump).astype(np.float32)     # t is the z-depth: the rays have z = 1


def walk(num_frames: int) -> np.ndarray:
  """`(T, 4, 4)` poses down the corridor at eye height, looking left and right as it goes."""
  poses = np.tile(np.eye(4, dtype=np.float32), (num_frames, 1, 1))
  for i in range(num_frames):
    yaw = 0.9 * np.sin(i / 40.0)
    forward = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    right = np.array([np.sin(yaw), -np.cos(yaw), 0.0])
    poses[i, :3, 0], poses[i, :3, 1], poses[i, :3, 2] = right, (0.0, 0.0, -1.0), forward
    poses[i, :3, 3] = (0.3 + (LENGTH - 0.6) * i / max(num_frames - 1, 1),
                       0.3 * np.sin(i / 70.0), 1.4)
  return poses


def _data(num_frames: int, height: int, width: int):
  import jaxfusion as jf
  camera = jf.Camera(0.6 * width, 0.6 * width, (width - 1) / 2, (height - 1) / 2)
  poses = walk(num_frames)
  depth = [corridor_depth(p, camera, height, width) for p in poses]
  rng = np.random.default_rng(0)
  probs = rng.dirichlet(np.ones(K), (8, height, width)).astype(np.float32)
  var = rng.uniform(0.0, 0.05, (8, height, width, K)).astype(np.float32)
  frames = [jf.Frame(d, p, probs[i % 8], var[i % 8]) for i, (d, p) in enumerate(zip(depth, poses))]
  return frames, camera


def _mapper(factor: int):
  import jaxfusion as jf
  rule = jf.rules.robust()
  geometry = jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=2**10)
  return jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=2**14, geometry=geometry,
                   growth_factor=factor), rule


def final_capacities(num_frames: int, height: int, width: int, factor: int) -> tuple:
  """`(slots, blocks)` a growing `Mapper` ends the walk with (a pilot run, untimed)."""
  frames, camera = _data(num_frames, height, width)
  mapper, _ = _mapper(factor)
  for frame in frames:
    mapper.fuse(frame, camera)
  return mapper.capacity, mapper.state.geometry.capacity


def run_one(num_frames: int, height: int, width: int, factor: int, final=None) -> dict:
  """One configuration, in this process: the growing run and the fixed-capacity baseline of
  `final = (slots, blocks)` (default: a pilot run's, `final_capacities`), in turns of `TURN`
  frames — frames t … t + TURN − 1 into the growing map, then into the fixed one — so that
  both see the same load of the machine (its speed drifts by 20 % over minutes) and each
  runs warm (frame by frame in turn, each frame finds the caches full of the other map's).
  The fixed map's program is compiled before, the growing map's in the run, as a user's."""
  import jax
  import jaxfusion as jf
  if final is None:
    final = final_capacities(num_frames, height, width, factor)
  frames, camera = _data(num_frames, height, width)
  mapper, rule = _mapper(factor)
  config = jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=int(final[1]))
  def fresh():
    return jf.init_map(capacity=int(final[0]), num_classes=K, voxel_size=0.05, rule=rule,
                       geometry=config)
  jax.block_until_ready(jf.fuse_frame(fresh(), frames[0], camera, rule))
  state, seconds, fixed = fresh(), [], []
  for turn in range(0, len(frames), TURN):
    for frame in frames[turn:turn + TURN]:
      start = time.perf_counter()
      jax.block_until_ready(mapper.fuse(frame, camera))
      seconds.append(time.perf_counter() - start)
    for frame in frames[turn:turn + TURN]:
      start = time.perf_counter()
      state = jf.fuse_frame(state, frame, camera, rule)
      jax.block_until_ready(state)
      fixed.append(time.perf_counter() - start)
  grew = sorted({t for t, _, _ in mapper.growths} | {t for t, _, _ in mapper.geometry_growths})
  if (mapper.capacity, mapper.state.geometry.capacity) != tuple(final):
    raise RuntimeError(f"the walk ended at {mapper.capacity} slots and "
                       f"{mapper.state.geometry.capacity} blocks, not the pilot's {final}")
  seconds, fixed = np.array(seconds), np.array(fixed)
  median = float(np.median(seconds[1:]))
  later = [t for t in grew if t > 0]
  return {
      "growth_factor": factor,
      "semantic_growths": [list(g) for g in mapper.growths],
      "geometry_growths": [list(g) for g in mapper.geometry_growths],
      "voxels": int(mapper.state.num_occupied), "dropped": int(mapper.state.num_dropped),
      "blocks": int(mapper.state.geometry.num_blocks),
      "final_capacity": mapper.capacity, "final_blocks": mapper.state.geometry.capacity,
      "first_frame_s": float(seconds[0]),
      "fuse_s": float(seconds[1:].sum()), "fixed_s": float(fixed[1:].sum()),
      "growth_share": float((seconds[1:].sum() - fixed[1:].sum()) / seconds[1:].sum()),
      "median_ms": 1e3 * median, "fixed_median_ms": 1e3 * float(np.median(fixed[1:])),
      "growth_frames": [{"frame": t, "s": float(seconds[t])} for t in later],
      "growth_excess_s": float(sum(seconds[t] - median for t in later)),
      "worst_frame": int(1 + np.argmax(seconds[1:])),
      "worst_frame_s": float(seconds[1:].max()),
  }


def host_apart() -> bool:
  """Runs XLA's threads on the last CPU of this process and the calling (Python) thread on the
  others, as a host beside an accelerator: the frames compute while the host works on the next
  one, instead of the two taking the same cores in turn. Call before JAX is first used (its
  thread pools start then, on the CPUs allowed at that moment; later threads of JAX's could
  land on the host's CPUs). False, and nothing changed, with fewer than 2 CPUs or where
  thread affinity cannot be set."""
  if not hasattr(os, "sched_setaffinity"):
    return False
  cpus = sorted(os.sched_getaffinity(0))
  if len(cpus) < 2:
    return False
  import jax
  import jax.numpy as jnp
  os.sched_setaffinity(0, {cpus[-1]})          # 0: this thread; threads it starts inherit it
  jax.block_until_ready(jax.jit(lambda x: x @ x + 1)(jnp.ones((256, 256))))
  os.sched_setaffinity(0, set(cpus[:-1]))
  return True


def steady_loops(num_frames: int = 600, height: int = 120, width: int = 160,
                 capacities: tuple = (2**20, 2**14), turns: int = 12) -> dict:
  """What a `Mapper` frame costs beside `fuse_frame` between growths: both maps allocated at
  the walk's final capacities (`capacities = (slots, blocks)`; nothing grows), all programs
  compiled first, then `turns` turns of the walk's frames in which each of four loops fuses
  the next `num_frames // turns` frames — a plain loop (what users write: a call returns once
  its frame is dispatched; one `block_until_ready` at the turn's end) and a loop that waits
  for each frame (as `run_one` times frames), each of the `Mapper` and of `fuse_frame`.
  Each loop has its own map of the same frames. Returns ms per frame, the medians over
  turns, and the turns' values."""
  import jax
  import jaxfusion as jf
  frames, camera = _data(num_frames, height, width)
  rule = jf.rules.robust()
  slots, blocks = (int(c) for c in capacities)

  def mapper():
    return jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=slots,
                     geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=blocks))

  def fixed():
    return jf.init_map(capacity=slots, num_classes=K, voxel_size=0.05, rule=rule,
                       geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=blocks))

  mappers = {"mapper_plain": mapper(), "mapper_waiting": mapper()}
  states = {"fuse_frame_plain": fixed(), "fuse_frame_waiting": fixed()}
  for m in mappers.values():          # compiles the three programs (and warms the caches)
    jax.block_until_ready(m.fuse(frames[0], camera))
  for name in states:
    states[name] = jax.block_until_ready(jf.fuse_frame(states[name], frames[0], camera, rule))
  step = (num_frames - 1) // turns
  times = {name: [] for name in ("mapper_plain", "fuse_frame_plain", "mapper_waiting",
                                 "fuse_frame_waiting")}
  for turn in range(turns):
    chunk = frames[1 + turn * step:1 + (turn + 1) * step]
    start = time.perf_counter()
    for frame in chunk:
      mappers["mapper_plain"].fuse(frame, camera)
    jax.block_until_ready(mappers["mapper_plain"].state)
    times["mapper_plain"].append(time.perf_counter() - start)
    start = time.perf_counter()
    state = states["fuse_frame_plain"]
    for frame in chunk:
      state = jf.fuse_frame(state, frame, camera, rule)
    states["fuse_frame_plain"] = jax.block_until_ready(state)
    times["fuse_frame_plain"].append(time.perf_counter() - start)
    start = time.perf_counter()
    for frame in chunk:
      jax.block_until_ready(mappers["mapper_waiting"].fuse(frame, camera))
    times["mapper_waiting"].append(time.perf_counter() - start)
    start = time.perf_counter()
    state = states["fuse_frame_waiting"]
    for frame in chunk:
      state = jax.block_until_ready(jf.fuse_frame(state, frame, camera, rule))
    states["fuse_frame_waiting"] = state
    times["fuse_frame_waiting"].append(time.perf_counter() - start)
  ms = {name: [1e3 * t / step for t in values] for name, values in times.items()}
  return {"frames_per_turn": step, "turns": turns, "height": height, "width": width,
          "capacities": [slots, blocks],
          "median_ms": {name: float(np.median(v)) for name, v in ms.items()},
          "turn_ms": ms}


def compile_costs(height: int = 120, width: int = 160, repeats: int = 3) -> list:
  """What a growth compiles, program by program, at the walk's frame size and its first
  capacities (2^16 slots, 2^12 blocks; fresh programs each time, medians of `repeats`
  lower + compile): the programs a `Mapper` frame runs (the capacity-free half,
  `fusion.prepare_frame`, compiled once; the semantic and geometry tables' halves, compiled
  for each capacity), `fuse_frame` in one program (both layers; the semantic layer alone) for
  comparison, and the programs that the CPU replaces by NumPy (the rehashes `state.grown_map`
  and `tsdf.grown_tsdf`, the room check's lookup `hashing.count_missing`), which an
  accelerator still compiles. Rows `{"program", "lower_s", "compile_s"}`."""
  import jax
  import jax.numpy as jnp
  import jaxfusion as jf
  from jaxfusion import fusion, hashing, state as state_lib, tsdf
  frames, camera = _data(1, height, width)
  rule = jf.rules.robust()
  def make(geometry=True):
    return jf.init_map(capacity=2**16, num_classes=K, voxel_size=0.05, rule=rule,
                       geometry=jf.tsdf.TSDFConfig(voxel_size=0.05, capacity=2**12)
                       if geometry else None)
  full, plain = make(), make(False)
  n = height * width
  keys, active = jnp.zeros((n, 3), jnp.int32), jnp.ones(n, bool)
  settings = tsdf.settings_only(full.geometry)
  prepared = fusion.prepare_frame(full.voxel_size, frames[0], camera, rule, settings)
  depth, pose = jnp.asarray(frames[0].depth), jnp.asarray(frames[0].T_world_cam)

  def fresh(fun, **static):
    # A new function each time, so that nothing traced or compiled before is reused.
    return lambda: jax.jit(lambda *a, **k: fun(*a, **k), static_argnames=tuple(static))

  programs = (
      ("prepare_frame (the frame's half, compiled once)",
       fresh(lambda v, f, s: fusion.prepare_frame_unchecked(v, f, camera, rule, s)),
       (full.voxel_size, frames[0], settings), {}),
      ("fuse_prepared (the semantic table's half)",
       fresh(lambda st, p: fusion.fuse_prepared_unchecked(st, p, camera, rule)),
       (plain, prepared), {}),
      ("integrate_blocks (the geometry table's half)",
       fresh(lambda g, b, d, t: tsdf.integrate_blocks_unchecked(g, b, d, t, camera)),
       (full.geometry, prepared.blocks, depth, pose), {}),
      ("fuse_frame, both layers in one program", fresh(fusion.fuse_frame_unchecked),
       (full, frames[0], camera, rule), {}),
      ("fuse_frame, semantic layer", fresh(fusion.fuse_frame_unchecked),
       (plain, frames[0], camera, rule), {}),
      ("grown_map (semantic rehash; NumPy on the CPU)",
       fresh(state_lib.grown_map.__wrapped__, capacity=0),
       (plain, state_lib.prior_row(plain, rule)), {"capacity": 2**18}),
      ("grown_tsdf (block rehash; NumPy on the CPU)",
       fresh(tsdf.grown_tsdf.__wrapped__, capacity=0), (full.geometry,), {"capacity": 2**14}),
      ("count_missing (room check; NumPy on the CPU)",
       fresh(hashing.count_missing.__wrapped__, max_probes=0),
       (plain.keys, keys, active), {"max_probes": plain.max_probes}),
  )
  rows = []
  for name, make_jit, args, kwargs in programs:
    lowers, compiles = [], []
    for _ in range(repeats):
      jitted = make_jit()        # a new jit object: nothing cached in memory
      start = time.perf_counter()
      lowered = jitted.lower(*args, **kwargs)
      lowers.append(time.perf_counter() - start)
      start = time.perf_counter()
      lowered.compile()
      compiles.append(time.perf_counter() - start)
    rows.append({"program": name, "lower_s": float(np.median(lowers)),
                 "compile_s": float(np.median(compiles))})
  return rows


def table(result: dict) -> str:
  first = result["runs"][0]
  lines = [
      f"{result['frames']} frames at {result['height']}×{result['width']} down a "
      f"{LENGTH:g} m corridor, K = {K}, D+R, 5 cm voxels and blocks; in the end "
      f"{first['voxels']:,} voxels ({first['dropped']} dropped) and {first['blocks']:,} blocks.",
      "",
      "| Mapper | growths (semantic + geometry) | fuse s (fixed map s) | growth share | "
      "growth frames' excess, % of fuse | median frame ms (fixed map) | "
      "growth frames, s each | worst frame s | first frame s |",
      "|---|---|---|---|---|---|---|---|---|",
  ]
  for name, r in zip((c[0] for c in CONFIGS), result["runs"]):
    lines.append(
        f"| {name} | {len(r['semantic_growths'])} + {len(r['geometry_growths'])} | "
        f"{r['fuse_s']:.1f} ({r['fixed_s']:.1f}) | {100 * r['growth_share']:.0f} % | "
        f"{100 * r['growth_excess_s'] / r['fuse_s']:.0f} % | "
        f"{r['median_ms']:.1f} ({r['fixed_median_ms']:.1f}) | "
        + ", ".join(f"{g['s']:.2f}" for g in r["growth_frames"])
        + f" | {r['worst_frame_s']:.2f} (frame {r['worst_frame']}) | {r['first_frame_s']:.1f} |")
  return "\n".join(lines)


def _child_env() -> dict:
  """The environment of a child run: JAX's own cache setting (a user's, or the test suite's)
  left out, since it would warm the first run."""
  return {k: v for k, v in os.environ.items() if k != "JAX_COMPILATION_CACHE_DIR"}


def _child(env: dict, frames: int, height: int, width: int, factor: int, *extra) -> dict:
  """One `--one` run in a process of its own (it compiles its own programs, as a user's run
  would): its JSON record."""
  done = subprocess.run([sys.executable, "-m", "bench.growth", "--one", str(frames),
                         str(height), str(width), str(factor), *extra],
                        capture_output=True, text=True, check=True, env=env,
                        cwd=pathlib.Path(__file__).parent.parent)
  return json.loads(done.stdout.strip().splitlines()[-1])


def overlap_pairs(pairs: int, frames: int, height: int, width: int) -> dict:
  """Factor 4 with a growth's compile and rehash overlapped (the default) and one after the
  other (`--not-overlapped`), `pairs` times each, in turns (not overlapped first), each run in
  a process of its own against the same pilot's final capacities: the machine's drift over
  minutes reaches both alike. Records every run, and per mode the medians over the runs of
  each growth frame, the growth frames' excess and the worst frame."""
  env = _child_env()
  final = _child(env, frames, height, width, 4, "--pilot")
  runs = {"not_overlapped": [], "overlapped": []}
  for _ in range(pairs):
    for mode, extra in (("not_overlapped", ("--not-overlapped",)), ("overlapped", ())):
      runs[mode].append(_child(env, frames, height, width, 4, "--final", *map(str, final),
                               *extra))
  medians = {}
  for mode, records in runs.items():
    medians[mode] = {
        "growth_frames_s": [float(np.median([r["growth_frames"][i]["s"] for r in records]))
                            for i in range(len(records[0]["growth_frames"]))],
        "growth_frame_ids": [g["frame"] for g in records[0]["growth_frames"]],
        "excess_share": float(np.median([r["growth_excess_s"] / r["fuse_s"] for r in records])),
        "growth_share": float(np.median([r["growth_share"] for r in records])),
        "worst_frame_s": float(np.median([r["worst_frame_s"] for r in records])),
        "fixed_s": float(np.median([r["fixed_s"] for r in records])),
    }
  return {"frames": frames, "height": height, "width": width, "pairs": pairs,
          "final": list(final), "runs": runs, "medians": medians}


def overlap_table(result: dict) -> str:
  lines = [f"Factor 4, {result['pairs']} runs of each in turns "
           f"({result['frames']} frames at {result['height']}×{result['width']}); medians "
           "over the runs (every run's value in brackets).", "",
           "| growth | growth frames, s each | growth frames' excess, % of fuse | "
           "growth share | worst frame s | fixed map s |", "|---|---|---|---|---|---|"]
  for mode, name in (("not_overlapped", "rehash, then compile"),
                     ("overlapped", "compile while a worker thread rehashes")):
    med, records = result["medians"][mode], result["runs"][mode]
    frames = ", ".join(
        f"{s:.2f} (" + " ".join(f"{r['growth_frames'][i]['s']:.2f}" for r in records) + ")"
        for i, s in enumerate(med["growth_frames_s"]))
    lines.append(
        f"| {name} | {frames} | {100 * med['excess_share']:.1f} % ("
        + " ".join(f"{100 * r['growth_excess_s'] / r['fuse_s']:.1f}" for r in records)
        + f") | {100 * med['growth_share']:.0f} % | {med['worst_frame_s']:.2f} ("
        + " ".join(f"{r['worst_frame_s']:.2f}" for r in records)
        + f") | {med['fixed_s']:.1f} |")
  return "\n".join(lines)


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(prog="python -m bench.growth",
                                   description=__doc__.split("\n")[0])
  parser.add_argument("--quick", action="store_true", help="300 frames at 60×80")
  parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results"))
  parser.add_argument("--one", nargs=4, type=int, help=argparse.SUPPRESS)   # a child run
  parser.add_argument("--final", nargs=2, type=int, help=argparse.SUPPRESS)  # its baseline
  parser.add_argument("--pilot", action="store_true", help=argparse.SUPPRESS)
  parser.add_argument("--not-overlapped", action="store_true", help=argparse.SUPPRESS)
  parser.add_argument("--overlap-pairs", type=int, metavar="N",
                      help="only factor 4, N runs with a growth's compile and rehash "
                           "overlapped and N without, in turns (writes growth_overlap.json)")
  parser.add_argument("--compiles", action="store_true",
                      help="only what a growth compiles, program by program "
                           "(writes growth_compiles.json)")
  parser.add_argument("--steady", action="store_true",
                      help="only a Mapper frame beside fuse_frame between growths, in plain "
                           "and waiting loops (writes growth_steady.json)")
  parser.add_argument("--host-apart", action="store_true",
                      help="with --steady: XLA's threads on one CPU, Python on the others "
                           "(host_apart; writes growth_steady_apart.json)")
  args = parser.parse_args(argv)
  if args.steady:
    apart = args.host_apart and host_apart()
    if args.host_apart and not apart:
      raise SystemExit("--host-apart needs at least 2 CPUs and thread affinity")
    result = steady_loops(*((120, 60, 80) if args.quick else ()), turns=4 if args.quick else 12)
    result["host_apart"] = apart
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = "growth_steady" + ("_apart" if apart else "") + ("_quick" if args.quick else "")
    (out / f"{name}.json").write_text(json.dumps(result, indent=1))
    med = result["median_ms"]
    print(f"| loop ({result['height']}×{result['width']}, {result['capacities'][0]} slots, "
          f"{result['capacities'][1]} blocks{', host apart' if apart else ''}) | "
          "Mapper ms/frame | fuse_frame ms/frame | ratio |\n|---|---|---|---|")
    for loop in ("plain", "waiting"):
      a, b = med[f"mapper_{loop}"], med[f"fuse_frame_{loop}"]
      print(f"| {loop} | {a:.2f} | {b:.2f} | {a / b:.2f} |")
    return
  if args.compiles:
    height, width = (60, 80) if args.quick else (120, 160)
    rows = compile_costs(height, width, repeats=1 if args.quick else 3)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / ("growth_compiles_quick.json" if args.quick else "growth_compiles.json")).write_text(
        json.dumps({"height": height, "width": width, "programs": rows}, indent=1))
    print(f"| program ({height}×{width}, 2^16 slots, 2^12 blocks) | lower s | compile s |\n"
          "|---|---|---|")
    for r in rows:
      print(f"| {r['program']} | {r['lower_s']:.2f} | {r['compile_s']:.2f} |")
    return
  if args.one:
    if os.environ.get("BENCH_GROWTH_CACHE"):
      from jaxfusion.lab import compile_cache   # the `jaxfusion` commands' cache, as they use it
      compile_cache.enable()
    if args.not_overlapped:
      from jaxfusion import mapper   # the comparison: a growth's rehash, then its compile
      mapper._COMPILE_WHILE_GROWING = False   # pylint: disable=protected-access
    frames, height, width, factor = args.one
    if args.pilot:
      print(json.dumps(final_capacities(frames, height, width, factor)))
    else:
      print(json.dumps(run_one(frames, height, width, factor, args.final)))
    return
  frames, height, width = (300, 60, 80) if args.quick else (2000, 120, 160)
  walk_args = (frames, height, width)
  if args.overlap_pairs:
    result = overlap_pairs(args.overlap_pairs, *walk_args)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / ("growth_overlap_quick.json" if args.quick else "growth_overlap.json")).write_text(
        json.dumps(result, indent=1))
    print(overlap_table(result))
    return
  runs = []
  for name, factor, cached, overlapped in CONFIGS:
    # A process per configuration: each compiles its own programs, as a user's run would.
    with tempfile.TemporaryDirectory() as cache:
      env = _child_env()
      if cached:
        env.update(JAXFUSION_COMPILE_CACHE=cache, BENCH_GROWTH_CACHE="1")
      extra = () if overlapped else ("--not-overlapped",)
      # A pilot learns the final capacities of the fixed baseline (and, for the cached
      # configuration, is the first run that fills the cache); the timed run is the second.
      final = _child(env, *walk_args, factor, "--pilot", *extra)
      runs.append(_child(env, *walk_args, factor, "--final", *map(str, final), *extra))
    runs[-1]["persistent_cache"] = cached
    runs[-1]["overlapped"] = overlapped
    print(f"{name}: {runs[-1]['fuse_s']:.1f} s", file=sys.stderr)
  result = {"frames": frames, "height": height, "width": width, "runs": runs}
  out = pathlib.Path(args.out)
  out.mkdir(parents=True, exist_ok=True)
  (out / ("growth_quick.json" if args.quick else "growth.json")).write_text(
      json.dumps(result, indent=1))
  print(table(result))


if __name__ == "__main__":
  main()
