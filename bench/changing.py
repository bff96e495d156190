"""`python -m bench.changing [--quick] [--out DIR]`: what a changing world and changing poses
cost (docs/equations.md §10–§11).

On the bench room (`bench.scene`, 640×480, K = 13, MC-like variances), 0.05 m voxels, maps of
2^18 slots filled to a realistic load first (the measured frames and `--load-frames` more of the
room, each fused with the public `fuse_frame`; C, the load and the drops of every map are in the
results), in one process:

1. free-space clearing: the public `fuse_frame` of one frame on a map with clearing off and on
   (`init_map(..., free_space=True)`), for D+R and for Bayes. The free-space pass (a projection
   of every one of the C slots against a depth pyramid, §10.4) costs the difference; target: at
   most 20 % of a D+R frame;
2. de-integration, Bayes: `reintegrate` of a stack of T frames (a pose correction of up to
   0.5° and 2 cm, old → new and back on alternate calls, so that the map always holds what is
   taken out) divided by T, against `fuse_sequence` of the same T frames divided by T (on a copy
   of the same map); target: re-integrating at most 2.5× fusing. Also `unfuse_frame` of one
   frame against `fuse_frame` of the same frame put back, per frame;
3. the same as 2 on a map with the geometry layer (`TSDFConfig(voxel_size=0.05)`), whose TSDF is
   de-integrated in the same calls.

Every call is a public entry point as users call it (jitted, the map donated), ended with
`block_until_ready`; the variants of one measurement are called in turn, repeat after repeat,
so that all see the same machine load; each figure is the median of the repeats after a warm-up
call (the first call, compile included, is reported apart). Writes `<out>/changing.json`
(default `bench/results/`; `--quick` writes nothing unless `--out` is given) and prints a
Markdown table. The load average at the start and at the end is in the JSON: compare runs
taken on a quiet machine only.
"""

import argparse
import dataclasses
import json
import os
import pathlib
import time
import warnings
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

import jaxfusion as jf
from bench import geometry as geometry_bench
from bench import scene
from bench import suite
from jaxfusion import deintegration


@dataclasses.dataclass
class Config:
  """What to measure: `full()` is the documented run, `quick()` a smoke run of a few seconds."""
  height: int = 480
  width: int = 640
  num_classes: int = 13
  measured_frames: int = 8        # T: the frames timed, and the stack reintegrate moves
  load_frames: int = 64           # more frames of the room fused first (realistic load)
  chunk: int = 8                  # load frames rendered at a time (host memory)
  capacity: int = 2**18           # C
  voxel_size: float = 0.05
  geometry_voxel_size: float = 0.05
  repeats: int = 15
  rotation_deg: float = 0.5       # the largest pose correction, reached at the last frame
  translation_m: float = 0.02

  @classmethod
  def full(cls):
    return cls()

  @classmethod
  def quick(cls):
    return cls(height=60, width=80, measured_frames=2, load_frames=2, chunk=2, capacity=2**14,
               voxel_size=0.1, geometry_voxel_size=0.1, repeats=2)


def corrected_poses(poses: np.ndarray, rotation_deg: float, translation_m: float) -> np.ndarray:
  """`(T, 4, 4)` the poses after a loop-closure-like correction: frame t moved by a world-frame
  rotation about z of `rotation_deg·(t+1)/T` and a translation of `translation_m·(t+1)/T`."""
  count = poses.shape[0]
  out = np.empty_like(poses)
  direction = np.array([1.0, 1.0, 0.5]) / np.linalg.norm([1.0, 1.0, 0.5])
  for t in range(count):
    share = (t + 1) / count
    a = np.deg2rad(rotation_deg * share)
    corr = np.eye(4)
    corr[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    corr[:3, 3] = translation_m * share * direction
    out[t] = (corr @ poses[t].astype(np.float64)).astype(poses.dtype)
  return out


def _timed(fn: Callable[[], object]):
  t0 = time.perf_counter()
  out = jax.block_until_ready(fn())
  return out, time.perf_counter() - t0


class _Map:
  """One donated map, its rule and its compile-included first call."""

  def __init__(self, name, rule, config, *, free_space=False, geometry=None):
    self.name, self.rule = name, rule
    self.state = jf.init_map(capacity=config.capacity, num_classes=config.num_classes,
                             voxel_size=config.voxel_size, rule=rule, free_space=free_space,
                             geometry=geometry)
    self.first_call_s = None

  def fuse(self, frame, camera) -> float:
    self.state, seconds = _timed(lambda: jf.fuse_frame(self.state, frame, camera, self.rule))
    if self.first_call_s is None:
      self.first_call_s = seconds
    return seconds

  def stats(self) -> dict:
    stats = jf.map_stats(self.state)
    out = {"capacity": stats["capacity"], "occupied": stats["occupied"],
           "load": stats["load_factor"], "dropped": stats["dropped"]}
    if "free" in stats:
      out["free"] = stats["free"]
    geo = self.state.geometry
    if geo is not None:
      out["geometry"] = {"block_capacity": geo.capacity, "blocks": int(geo.num_blocks),
                         "block_load": int(geo.num_blocks) / geo.capacity,
                         "dropped": int(geo.num_dropped),
                         "capped_voxels": jf.tsdf.capped_voxels(geo)}
    return out


def _device_frames(frames: scene.BenchFrames, poses=None) -> list:
  poses = frames.poses if poses is None else poses
  return [jax.device_put(jf.Frame(frames.depth[t], poses[t], frames.probs[t], frames.var[t]))
          for t in range(frames.depth.shape[0])]


def _load(maps, measured, config, log) -> int:
  """Fuses the measured frames, then `config.load_frames` more of the room, into every map;
  returns the frames fused."""
  fused = 0
  for frame in _device_frames(measured):
    for m in maps:
      m.fuse(frame, measured.camera)
    fused += 1
  for start in range(0, config.load_frames, config.chunk):
    count = min(config.chunk, config.load_frames - start)
    chunk = scene.make_frames(count, height=config.height, width=config.width,
                              num_classes=config.num_classes, seed=1000 + start)
    for frame in _device_frames(chunk):
      for m in maps:
        m.fuse(frame, chunk.camera)
      fused += 1
    log(f"  loaded {fused} frames: " + ", ".join(
        f"{m.name} {int(m.state.num_occupied)} voxels" for m in maps))
  return fused


def _row(seconds, per: int = 1) -> dict:
  s = float(np.median(seconds)) / per
  return {"ms_per_frame": 1e3 * s, "frames_per_s": 1.0 / s, "calls": len(seconds)}


def free_space_rows(maps: dict, frames: list, camera, repeats: int) -> dict:
  """`fuse_frame` of the measured frames in turn on each map of `maps`, interleaved."""
  times = {name: [] for name in maps}
  for name, m in maps.items():     # warm-up (compiled during the load)
    m.fuse(frames[0], camera)
  for r in range(repeats):
    frame = frames[r % len(frames)]
    for name, m in maps.items():
      times[name].append(m.fuse(frame, camera))
  return {name: _row(t) for name, t in times.items()}


def change_rows(m: _Map, measured: scene.BenchFrames, config) -> dict:
  """Per frame: `fuse_sequence` of the T measured frames / T (on a copy of the map),
  `reintegrate` of the same stack / T (old → new poses, and back on the next call),
  `unfuse_frame` of each frame and `fuse_frame` of it put back (on the map)."""
  camera, rule = measured.camera, m.rule
  count = measured.depth.shape[0]
  poses = [measured.poses, corrected_poses(measured.poses, config.rotation_deg,
                                           config.translation_m)]
  stack = jax.device_put(measured.stacked())
  stacks = [stack._replace(T_world_cam=jnp.asarray(p)) for p in poses]
  singles = [_device_frames(measured, p) for p in poses]
  copy = {"state": jax.tree.map(jnp.copy, m.state)}
  times = {"fuse_sequence": [], "reintegrate": [], "unfuse_frame": [], "fuse_frame": []}
  first = {}
  current = 0

  def one_round(record: bool):
    nonlocal current
    copy["state"], s = _timed(lambda: jf.fuse_sequence(copy["state"], stacks[current], camera,
                                                       rule))
    (times["fuse_sequence"] if record else first.setdefault("fuse_sequence", [])).append(s)
    new = 1 - current
    m.state, s = _timed(lambda: jf.reintegrate(m.state, stack, poses[current], poses[new],
                                               camera, rule))
    (times["reintegrate"] if record else first.setdefault("reintegrate", [])).append(s)
    current = new
    for t in range(count):
      frame = singles[current][t]
      m.state, s = _timed(lambda f=frame: jf.unfuse_frame(m.state, f, camera, rule))
      (times["unfuse_frame"] if record else first.setdefault("unfuse_frame", [])).append(s)
      m.state, s = _timed(lambda f=frame: jf.fuse_frame(m.state, f, camera, rule))
      (times["fuse_frame"] if record else first.setdefault("fuse_frame", [])).append(s)

  with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always", deintegration.CappedWeightWarning)
    one_round(record=False)         # warm-up: compiles every call
    for _ in range(config.repeats):
      one_round(record=True)
  rows = {"fuse_sequence": _row(times["fuse_sequence"], count),
          "reintegrate": _row(times["reintegrate"], count),
          "unfuse_frame": _row(times["unfuse_frame"]),
          "fuse_frame": _row(times["fuse_frame"])}
  rows["first_call_s"] = {k: v[0] for k, v in first.items()}
  rows["reintegrate_over_fuse_sequence"] = (rows["reintegrate"]["ms_per_frame"]
                                            / rows["fuse_sequence"]["ms_per_frame"])
  rows["unfuse_over_fuse_frame"] = (rows["unfuse_frame"]["ms_per_frame"]
                                    / rows["fuse_frame"]["ms_per_frame"])
  rows["capped_weight_warnings"] = sum(
      issubclass(w.category, deintegration.CappedWeightWarning) for w in caught)
  rows["stack"] = count
  return rows


def run(config: Config, log: Callable[[str], None] = lambda s: None) -> dict:
  """Every measurement of the module docstring; returns the results dict."""
  start = suite.machine()
  k = config.num_classes
  measured = scene.make_frames(config.measured_frames, height=config.height, width=config.width,
                               num_classes=k, seed=0)
  camera = measured.camera
  dr, bayes = jf.rules.robust(), jf.rules.bayes()
  # The geometry bench's block slots for the room at this voxel size (load ≤ ~0.4).
  blocks = geometry_bench._capacity(config.geometry_voxel_size)  # pylint: disable=protected-access
  tsdf_config = jf.TSDFConfig(voxel_size=config.geometry_voxel_size, capacity=blocks)
  maps = {"dr_off": _Map("D+R", dr, config),
          "dr_on": _Map("D+R free space", dr, config, free_space=True),
          "bayes_off": _Map("Bayes", bayes, config),
          "bayes_on": _Map("Bayes free space", bayes, config, free_space=True),
          "bayes_geometry": _Map("Bayes + TSDF", bayes, config, geometry=tsdf_config)}
  log(f"loading {len(maps)} maps of 2^{int(np.log2(config.capacity))} slots")
  fused = _load(list(maps.values()), measured, config, log)
  loaded = {name: m.stats() for name, m in maps.items()}
  first_fuse = {name: m.first_call_s for name, m in maps.items()}
  frames = _device_frames(measured)

  log("1. fuse_frame with free-space clearing off and on")
  fs = free_space_rows({n: maps[n] for n in ("dr_off", "dr_on", "bayes_off", "bayes_on")},
                       frames, camera, config.repeats)
  free_space = {}
  for rule in ("dr", "bayes"):
    off, on = fs[f"{rule}_off"]["ms_per_frame"], fs[f"{rule}_on"]["ms_per_frame"]
    free_space[rule] = {"off": fs[f"{rule}_off"], "on": fs[f"{rule}_on"],
                        "pass_ms": on - off, "pass_share_of_frame": (on - off) / off,
                        "pass_share_of_dr_frame": (on - off) / fs["dr_off"]["ms_per_frame"]}
  for name in ("dr_off", "dr_on", "bayes_on"):
    maps.pop(name).state = None     # free their memory

  log("2. reintegrate / unfuse_frame against fuse_sequence / fuse_frame, Bayes")
  change = change_rows(maps["bayes_off"], measured, config)
  log("3. the same with the geometry layer")
  change_geometry = change_rows(maps["bayes_geometry"], measured, config)
  try:
    end_load = os.getloadavg()
  except OSError:
    end_load = None
  return {
      "machine": start, "load_avg_at_start": start["load_avg_1_5_15"],
      "load_avg_at_end": end_load, "config": dataclasses.asdict(config),
      "frames_fused_before": fused, "maps": loaded, "first_fuse_frame_s": first_fuse,
      "geometry": dataclasses.asdict(tsdf_config), "free_space": free_space,
      "reintegrate": change, "reintegrate_geometry": change_geometry,
      "targets": {"free_space_pass_share_of_dr_frame_max": 0.2,
                  "reintegrate_over_fuse_max": 2.5},
  }


def _ms(row) -> str:
  return f"{row['ms_per_frame']:.2f} | {row['frames_per_s']:.1f}"


def to_markdown(r: dict) -> str:
  c = r["config"]
  m = r["maps"]
  loads = ", ".join(f"{name} {s['occupied']} ({s['load']:.2f})" for name, s in m.items())
  geo = m["bayes_geometry"]["geometry"]
  lines = [f"{c['height']}×{c['width']}, K = {c['num_classes']}, {c['voxel_size']} m voxels, "
           f"C = 2^{int(np.log2(c['capacity']))} = {c['capacity']} slots after "
           f"{r['frames_fused_before']} frames; voxels (load): {loads}; TSDF "
           f"{r['geometry']['voxel_size']} m, {geo['blocks']} of {geo['block_capacity']} blocks. "
           f"Load average at start {r['load_avg_at_start']}, at end {r['load_avg_at_end']}.", "",
           "| measure (per frame, median) | ms | frames/s | ratio | target |",
           "|---|---|---|---|---|"]
  for rule, label in (("dr", "D+R"), ("bayes", "Bayes")):
    f = r["free_space"][rule]
    lines += [f"| {label} `fuse_frame`, clearing off | {_ms(f['off'])} | | |",
              f"| {label} `fuse_frame`, clearing on | {_ms(f['on'])} | "
              f"{f['on']['ms_per_frame'] / f['off']['ms_per_frame']:.2f}× off | |",
              f"| {label} free-space pass (on − off) | {f['pass_ms']:.2f} | | "
              f"{f['pass_share_of_frame']:.0%} of its frame, {f['pass_share_of_dr_frame']:.0%} "
              f"of a D+R frame | ≤ 20 % of a D+R frame |"]
  for key, label in (("reintegrate", "Bayes"), ("reintegrate_geometry", "Bayes + TSDF")):
    x = r[key]
    lines += [f"| {label} `fuse_sequence` of {x['stack']} / {x['stack']} | "
              f"{_ms(x['fuse_sequence'])} | | |",
              f"| {label} `reintegrate` of {x['stack']} / {x['stack']} | {_ms(x['reintegrate'])} "
              f"| {x['reintegrate_over_fuse_sequence']:.2f}× fuse_sequence | ≤ 2.5× |",
              f"| {label} `fuse_frame` | {_ms(x['fuse_frame'])} | | |",
              f"| {label} `unfuse_frame` | {_ms(x['unfuse_frame'])} | "
              f"{x['unfuse_over_fuse_frame']:.2f}× fuse_frame | |"]
  capped = r["reintegrate_geometry"]["capped_weight_warnings"]
  if capped:
    lines += ["", f"{capped} calls warned of TSDF voxels at the weight cap."]
  return "\n".join(lines)


def main(argv=None) -> dict:
  parser = argparse.ArgumentParser(prog="python -m bench.changing",
                                   description=__doc__.split("\n")[0])
  parser.add_argument("--quick", action="store_true",
                      help="tiny sizes (60×80, 2 frames), a few seconds; writes nothing unless "
                      "--out is given")
  parser.add_argument("--out", default=None, help="output folder (default bench/results/)")
  args = parser.parse_args(argv)
  config = Config.quick() if args.quick else Config.full()
  result = {"command": "python -m bench.changing" + (" --quick" if args.quick else "")}
  result.update(run(config, log=lambda s: print(s, flush=True)))
  print(to_markdown(result))
  out = args.out
  if out is None and not args.quick:
    out = str(pathlib.Path(__file__).parent / "results")
  if out is not None:
    path = pathlib.Path(out)
    path.mkdir(parents=True, exist_ok=True)
    (path / "changing.json").write_text(json.dumps(result, indent=1))
    print(f"\nwrote {path / 'changing.json'}")
  return result


if __name__ == "__main__":
  main()
