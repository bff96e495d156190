"""`python -m bench.growth [--quick]`: what a growing map costs.

A camera walks along a corridor of rough walls (random depths 1–6 m, 5 cm voxels), so every
frame adds thousands of new voxels and a `Mapper` started at 2^14 slots grows several times.
It reports, per frame, the time of `Mapper.fuse` (median and max between growths, with the
growths apart) against `fuse_frame` on a map allocated at the final capacity from the start,
and the time of each `grow_map` against the capacity it grows to. Writes
`bench/results/growth.json` and prints a Markdown table.
"""

import argparse
import json
import pathlib
import time

import jax
import numpy as np

import jaxfusion as jf
from jaxfusion import state as state_lib

K = 13


def frames(num_frames: int, height: int, width: int, seed: int = 0):
  rng = np.random.default_rng(seed)
  for t in range(num_frames):
    depth = rng.uniform(1.0, 6.0, (height, width)).astype(np.float32)
    pose = np.eye(4, dtype=np.float32)
    pose[0, 3] = 0.8 * t
    probs = rng.dirichlet(np.ones(K), (height, width)).astype(np.float32)
    var = rng.uniform(0.0, 0.05, (height, width, K)).astype(np.float32)
    yield jf.Frame(depth, pose, probs, var)


def _timed(fn):
  start = time.perf_counter()
  out = fn()
  jax.block_until_ready(out)
  return out, time.perf_counter() - start


def run(num_frames: int, height: int, width: int) -> dict:
  camera = jf.Camera(0.6 * width, 0.6 * width, (width - 1) / 2, (height - 1) / 2)
  rule = jf.rules.robust()
  data = list(frames(num_frames, height, width))
  # Warm-up: compile the step at every capacity the run will reach, and the checks.
  mapper = jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=2**14)
  for frame in data:
    mapper.fuse(frame, camera)
  final_capacity = mapper.capacity
  grown_to = [c for _, _, c in mapper.growths]
  # Growing run, timed frame by frame (a frame whose call grew the map is a growth frame).
  mapper = jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=2**14)
  per_frame, growth_frames = [], []
  for t, frame in enumerate(data):
    before = len(mapper.growths)
    _, seconds = _timed(lambda f=frame: mapper.fuse(f, camera).rows)
    (growth_frames if len(mapper.growths) > before else per_frame).append((t, seconds))
  # grow_map alone, at each capacity the run grew to (from a map holding what it held then).
  grow_times = []
  replay = jf.Mapper(rule, num_classes=K, voxel_size=0.05, capacity=2**14)
  for t, frame in enumerate(data):
    for (when, old, new) in [g for g in mapper.growths if g[0] == t]:
      state = replay.state
      state_lib.grow_map(state, new, rule=rule)            # compile this shape once
      _, seconds = _timed(lambda s=state, n=new: state_lib.grow_map(s, n, rule=rule).rows)
      grow_times.append({"frame": when, "from": old, "to": new,
                         "voxels": int(state.num_occupied), "ms": 1e3 * seconds})
    replay.fuse(frame, camera)
  # The same frames on a map allocated at the final capacity: the flat baseline.
  state = jf.init_map(capacity=final_capacity, num_classes=K, voxel_size=0.05, rule=rule)
  state = jf.fuse_frame(state, data[0], camera, rule)      # compile
  state = jf.init_map(capacity=final_capacity, num_classes=K, voxel_size=0.05, rule=rule)
  baseline = []
  for frame in data:
    state, seconds = _timed(lambda s=state, f=frame: jf.fuse_frame(s, f, camera, rule))
    baseline.append(seconds)
  steady = np.array([s for _, s in per_frame]) * 1e3
  return {
      "frames": num_frames, "height": height, "width": width, "voxel_size": 0.05,
      "final_capacity": final_capacity, "grown_to": grown_to,
      "voxels": int(mapper.state.num_occupied), "dropped": int(mapper.state.num_dropped),
      "mapper_ms_median": float(np.median(steady)), "mapper_ms_max": float(steady.max()),
      "mapper_ms_first_half": float(np.median(steady[:len(steady) // 2])),
      "mapper_ms_second_half": float(np.median(steady[len(steady) // 2:])),
      "growth_frame_ms": [1e3 * s for _, s in growth_frames],
      "fixed_ms_median": float(np.median(baseline) * 1e3),
      "grow_map": grow_times,
  }


def table(r: dict) -> str:
  lines = [
      f"{r['frames']} frames at {r['height']}×{r['width']}, K = {K}, D+R, {r['voxel_size']} m "
      f"voxels; {r['voxels']} voxels in the end, {r['dropped']} dropped; capacity 2^14 → "
      + " → ".join(f"2^{int(np.log2(c))}" for c in r["grown_to"]),
      "",
      "| per frame | ms |", "|---|---|",
      f"| `Mapper.fuse` between growths, median (first half / second half) | "
      f"{r['mapper_ms_median']:.1f} ({r['mapper_ms_first_half']:.1f} / "
      f"{r['mapper_ms_second_half']:.1f}) |",
      f"| `Mapper.fuse` between growths, max | {r['mapper_ms_max']:.1f} |",
      f"| `fuse_frame` on a map allocated at 2^{int(np.log2(r['final_capacity']))}, median | "
      f"{r['fixed_ms_median']:.1f} |",
      f"| a frame that grows the map (count + `grow_map` + fuse), each | "
      + ", ".join(f"{ms:.0f}" for ms in r["growth_frame_ms"]) + " |",
      "",
      "| `grow_map` | voxels moved | ms |", "|---|---|---|",
  ]
  lines += [f"| 2^{int(np.log2(g['from']))} → 2^{int(np.log2(g['to']))} | {g['voxels']} | "
            f"{g['ms']:.1f} |" for g in r["grow_map"]]
  return "\n".join(lines)


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(prog="python -m bench.growth",
                                   description=__doc__.split("\n")[0])
  parser.add_argument("--quick", action="store_true", help="fewer, smaller frames")
  parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results"))
  args = parser.parse_args(argv)
  size = (60, 80, 40) if args.quick else (120, 160, 40)
  result = run(size[2], size[0], size[1])
  out = pathlib.Path(args.out)
  out.mkdir(parents=True, exist_ok=True)
  (out / "growth.json").write_text(json.dumps(result, indent=1))
  print(table(result))
  print(f"\nwrote {out / 'growth.json'}")


if __name__ == "__main__":
  main()
