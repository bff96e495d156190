"""`python -m bench.device [--quick] [--out DIR]`: the headline costs on whatever JAX backend is
present (CPU, GPU or TPU), in one run, beside nvblox's published numbers.

On the bench room (`bench.scene`, 640×480), in one process:

1. `fuse_frame` per rule of `jaxfusion.rules.PAPER_RULES` (the six), K = 13, 0.05 m voxels,
   a map of 2^18 slots after `warm_frames` frames of the room;
2. the geometry layer alone: `tsdf.integrate` per frame and `mesh.marching_cubes` of the layer
   (a TSDFState) per call, at 0.05 and 0.02 m (block slots from `bench.geometry._capacity`);
3. the MC front end: the shipped network's M dropout samples of one RGB frame
   (`models.sampling.mc_samples`, as `bench.suite.sampler_rows`; K is the net's) and
   `mc_moments` of an `(M, H, W, 13)` sample stack (as `bench.suite.mc_rows`);
4. `fuse_batch` (D+R) of B sequences × T frames at 240×320, from empty maps, in frames/s;
5. a `Mapper` frame (both layers, between growths) beside `fuse_frame`'s in a plain loop of the
   corridor walk (`bench.growth.steady_loops`, 120×160): where the device runs apart from the
   host, a frame's host work then overlaps the frame before.

Every call is ended with `block_until_ready`; each figure is the median of the repeats after a
warm-up call. Writes `<out>/device.json` (default `bench/results/`) and prints a Markdown table.
nvblox's figures are the published ones (RTX 3090, 5 cm), not measured here.
"""

import argparse
import dataclasses
import json
import pathlib
import time
from typing import Callable

import jax
import numpy as np

import jaxfusion as jf
from bench import geometry as geometry_bench
from bench import scene
from bench import suite
from jaxfusion import mesh as mesh_lib
from jaxfusion import tsdf

# nvblox's published per-frame costs at 5 cm on an RTX 3090 (ms).
NVBLOX = {"label": "nvblox, RTX 3090, published", "voxel_size": 0.05, "tsdf_ms": 0.5,
          "mesh_ms": 0.7}


@dataclasses.dataclass
class Config:
  """What to measure: `full()` is the documented run, `quick()` a smoke run of seconds."""
  height: int = 480
  width: int = 640
  num_classes: int = 13
  capacity: int = 2**18
  voxel_size: float = 0.05
  warm_frames: int = 4            # frames fused into every map before timing
  frames: int = 8                 # distinct frames cycled through while timing
  repeats: int = 10
  tsdf_voxel_sizes: tuple = (0.05, 0.02)
  tsdf_capacity: int = 0          # 0: `bench.geometry._capacity(voxel_size)`
  mc_samples: int = 16
  batch: int = 4                  # B
  batch_frames: int = 4           # T
  batch_height: int = 240
  batch_width: int = 320
  steady_frames: int = 241        # the Mapper's loop: frames, turns, (slots, blocks)
  steady_turns: int = 6
  steady_capacities: tuple = (2**20, 2**14)

  @classmethod
  def full(cls):
    return cls()

  @classmethod
  def quick(cls):
    return cls(height=60, width=80, num_classes=7, capacity=2**12, voxel_size=0.1,
               warm_frames=1, frames=2, repeats=2, tsdf_voxel_sizes=(0.1,),
               tsdf_capacity=2**10, mc_samples=2, batch=2, batch_frames=2, batch_height=30,
               batch_width=40, steady_frames=9, steady_turns=2,
               steady_capacities=(2**16, 2**12))


def _median_s(fn: Callable[[], object], repeats: int) -> float:
  return suite.median_time(fn, repeats)


def _row(seconds: float) -> dict:
  return {"ms_per_frame": 1e3 * seconds, "frames_per_s": 1.0 / seconds}


def backend() -> dict:
  """The JAX backend and its devices."""
  return {"default_backend": jax.default_backend(),
          "devices": [str(d) for d in jax.devices()],
          "device_kinds": [d.device_kind for d in jax.devices()],
          "jax": jax.__version__}


def fuse_rows(frames: scene.BenchFrames, config: Config) -> dict:
  """`fuse_frame` of each of the six paper rules, on a map warmed with `warm_frames` frames."""
  dev = [jax.device_put(frames.frame(t)) for t in range(frames.depth.shape[0])]
  warm, timed = dev[:config.warm_frames], dev[config.warm_frames:]
  rows = {}
  for name in jf.rules.PAPER_RULES:
    rule = jf.rules.by_name(name)
    holder = {"state": jf.init_map(capacity=config.capacity, num_classes=config.num_classes,
                                   voxel_size=config.voxel_size, rule=rule), "t": 0}
    for frame in warm:
      holder["state"] = jf.fuse_frame(holder["state"], frame, frames.camera, rule)

    def step(holder=holder, rule=rule):
      holder["state"] = jf.fuse_frame(holder["state"], timed[holder["t"] % len(timed)],
                                      frames.camera, rule)
      holder["t"] += 1
      return holder["state"]

    row = _row(_median_s(step, config.repeats))
    row["occupied"] = int(holder["state"].num_occupied)
    rows[name] = row
  return rows


def tsdf_rows(frames: scene.BenchFrames, config: Config) -> list:
  """`tsdf.integrate` per frame and `mesh.marching_cubes` per call, per voxel size."""
  dev = [(jax.device_put(frames.depth[t]), jax.device_put(frames.poses[t]))
         for t in range(frames.depth.shape[0])]
  rows = []
  for v in config.tsdf_voxel_sizes:
    capacity = config.tsdf_capacity or geometry_bench._capacity(v)  # pylint: disable=protected-access
    holder = {"state": tsdf.init_tsdf(voxel_size=v, capacity=capacity), "t": 0}

    def step(holder=holder):
      depth, pose = dev[holder["t"] % len(dev)]
      holder["state"] = tsdf.integrate(holder["state"], depth, pose, frames.camera)
      holder["t"] += 1
      return holder["state"]

    integrate_s = _median_s(step, max(config.repeats, len(dev)))
    geometry = holder["state"]
    mesh_s = _median_s(lambda: mesh_lib.marching_cubes(geometry), config.repeats)
    _, faces = mesh_lib.marching_cubes(geometry)
    stats = tsdf.tsdf_stats(geometry)
    rows.append({"voxel_size": v, "block_capacity": capacity, "blocks": stats["blocks"],
                 "triangles": int(len(faces)), "integrate_ms_per_frame": 1e3 * integrate_s,
                 "integrate_frames_per_s": 1.0 / integrate_s, "mesh_ms": 1e3 * mesh_s})
  return rows


def mc_rows(config: Config) -> dict:
  """The shipped net's M samples of one frame, and `mc_moments` of an (M, H, W, K) stack."""
  h, w, m = config.height, config.width, config.mc_samples
  out = {}
  try:
    from models import checkpoint  # pylint: disable=import-outside-toplevel
    from models import sampling  # pylint: disable=import-outside-toplevel
    model = checkpoint.load_pretrained()
    image = np.random.default_rng(0).integers(0, 256, (h, w, 3), dtype=np.uint8)
    key = jax.random.key(1)
    s = _median_s(lambda: sampling.mc_samples(model.graphdef, model.params, key, image,
                                              num_samples=m), config.repeats)
    out["network_samples"] = {"M": m, "height": h, "width": w,
                              "num_classes": model.config.num_classes, **_row(s)}
  except Exception as e:  # pylint: disable=broad-except
    out["network_samples"] = {"skipped": f"{type(e).__name__}: {e}"}
  rng = np.random.default_rng(0)
  logits = rng.normal(size=(m, h, w, config.num_classes)).astype(np.float32)
  samples = jax.device_put(jax.nn.softmax(logits, axis=-1))
  s = _median_s(lambda: jf.mc_moments(samples), config.repeats)
  out["mc_moments"] = {"M": m, "height": h, "width": w, "num_classes": config.num_classes,
                       **_row(s)}
  return out


def batch_row(config: Config) -> dict:
  """`fuse_batch` (D+R) of B sequences × T frames into B empty maps, per frame."""
  b, t = config.batch, config.batch_frames
  frames = scene.make_frames(b * t, height=config.batch_height, width=config.batch_width,
                             num_classes=config.num_classes, seed=21)
  stacked = jax.device_put(jax.tree.map(
      lambda x: x.reshape((b, t) + x.shape[1:]), frames.stacked()))
  rule = jf.rules.by_name("robust_dr")
  s = _median_s(lambda: jf.fuse_batch(stacked, frames.camera, rule, capacity=config.capacity,
                                      voxel_size=config.voxel_size), config.repeats)
  return {"B": b, "T": t, "height": config.batch_height, "width": config.batch_width,
          "rule": "robust_dr", "ms_per_call": 1e3 * s, "frames_per_s": b * t / s}


def mapper_row(config: Config) -> dict:
  """A `Mapper` frame beside `fuse_frame`'s, plain and waiting loops (`steady_loops`)."""
  from bench import growth
  result = growth.steady_loops(config.steady_frames, 120, 160, config.steady_capacities,
                               turns=config.steady_turns)
  return {"frames_per_turn": result["frames_per_turn"], "turns": result["turns"],
          "capacities": result["capacities"], **result["median_ms"]}


def run(config: Config, *, out_dir=None, log=print) -> dict:
  """Measures everything in the module docstring; writes `<out_dir>/device.json` if given."""
  t0 = time.perf_counter()
  results = {"backend": backend(), "machine": suite.machine(),
             "config": dataclasses.asdict(config), "nvblox": NVBLOX}
  log(f"backend: {results['backend']}")
  frames = scene.make_frames(config.warm_frames + config.frames, height=config.height,
                             width=config.width, num_classes=config.num_classes, seed=5)
  results["fuse_frame"] = fuse_rows(frames, config)
  log(f"fuse_frame: {results['fuse_frame']}")
  results["tsdf"] = tsdf_rows(frames, config)
  log(f"tsdf: {results['tsdf']}")
  results["mc"] = mc_rows(config)
  log(f"mc: {results['mc']}")
  results["fuse_batch"] = batch_row(config)
  log(f"fuse_batch: {results['fuse_batch']}")
  results["mapper"] = mapper_row(config)
  log(f"mapper: {results['mapper']}")
  results["wall_s"] = time.perf_counter() - t0
  if out_dir is not None:
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / "device.json").write_text(json.dumps(results, indent=2))
  return results


def _fmt(x: float) -> str:
  return f"{x:.3g}" if x < 100 else f"{x:.0f}"


def to_markdown(results: dict) -> str:
  """One table: what was measured, ours on this backend, nvblox's published figure."""
  c = results["config"]
  ours = f"ours, {results['backend']['default_backend']}"
  size = f"{c['width']}×{c['height']}"
  lines = [f"| measurement | {ours} | {NVBLOX['label']} |", "|---|---|---|"]
  for name, row in results["fuse_frame"].items():
    lines.append(f"| fuse_frame {jf.rules.PAPER_RULES[name][0]}, {size}, K={c['num_classes']}, "
                 f"{c['voxel_size']} m: ms/frame (frames/s) | {_fmt(row['ms_per_frame'])} "
                 f"({_fmt(row['frames_per_s'])}) | — |")
  for row in results["tsdf"]:
    at5 = abs(row["voxel_size"] - NVBLOX["voxel_size"]) < 1e-9
    lines.append(f"| TSDF integrate, {size}, {row['voxel_size']} m: ms/frame | "
                 f"{_fmt(row['integrate_ms_per_frame'])} | "
                 f"{NVBLOX['tsdf_ms'] if at5 else '—'} |")
    lines.append(f"| mesh (marching_cubes), {row['voxel_size']} m, {row['triangles']} "
                 f"triangles: ms | {_fmt(row['mesh_ms'])} | "
                 f"{NVBLOX['mesh_ms'] if at5 else '—'} |")
  net = results["mc"]["network_samples"]
  if "ms_per_frame" in net:
    lines.append(f"| shipped net, M={net['M']} samples, {size}, K={net['num_classes']}: ms/frame "
                 f"| {_fmt(net['ms_per_frame'])} | — |")
  else:
    lines.append(f"| shipped net samples | skipped ({net['skipped']}) | — |")
  mom = results["mc"]["mc_moments"]
  lines.append(f"| mc_moments (M={mom['M']}, {size}, K={mom['num_classes']}): ms/frame | "
               f"{_fmt(mom['ms_per_frame'])} | — |")
  b = results["fuse_batch"]
  lines.append(f"| fuse_batch D+R, B={b['B']}×T={b['T']}, {b['width']}×{b['height']}: frames/s | "
               f"{_fmt(b['frames_per_s'])} | — |")
  m = results["mapper"]
  for loop in ("plain", "waiting"):
    lines.append(f"| Mapper (both layers) beside fuse_frame, 160×120, a {loop} loop: ms/frame "
                 f"| {_fmt(m[f'mapper_{loop}'])} against {_fmt(m[f'fuse_frame_{loop}'])} "
                 f"({m[f'mapper_{loop}'] / m[f'fuse_frame_{loop}']:.2f}×) | — |")
  return "\n".join(lines)


def main(argv=None) -> dict:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--quick", action="store_true", help="tiny sizes, a smoke run")
  parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results"),
                      help="folder for device.json (default bench/results/)")
  args = parser.parse_args(argv)
  config = Config.quick() if args.quick else Config.full()
  results = run(config, out_dir=args.out)
  print(to_markdown(results))
  return results


if __name__ == "__main__":
  main()
