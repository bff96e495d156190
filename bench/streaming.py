"""Streaming: peak memory and throughput of a long ScanNet-format sequence read from disk a chunk
at a time (`jaxfusion sweep --data`, `tune.sweep_chunks`), against the in-memory path (the
whole sequence and its predictions loaded, then `tune.sweep_beta`) on the same frames.

The sequence: `--distinct` frames of the embedded world rendered at 640×480 and written in
ScanNet's layout (`datasets.export.save_scannet`), with 12-class predictions (the GT read into
the paper's ScanNet-12 label space), then repeated by symbolic links to `--frames` frame ids
(pass after pass through the same room, as a long scan of one room is): the disk holds only
the distinct frames, the reader reads every id. Each measurement runs in a fresh process;
peak memory is its maximum resident set size.

  python -m bench.streaming [--quick] [--frames 100 400 1600] [--out bench/results/streaming]

Rows of other lengths already in `--out` are kept (`--frames 3000` adds a length).
"""

import argparse
import json
import os
import resource
import subprocess
import sys
import time

import numpy as np

WORK = "outputs/streaming"


def _make(root: str, distinct: int, frames: int, height: int, width: int) -> tuple:
  """The ScanNet-format scene of `frames` ids and its predictions folder; returns their paths."""
  from jaxfusion import datasets  # pylint: disable=import-outside-toplevel
  from jaxfusion import sources  # pylint: disable=import-outside-toplevel
  from jaxfusion.datasets import export  # pylint: disable=import-outside-toplevel
  base = os.path.join(root, "base")
  if not os.path.isdir(os.path.join(base, "pose")):
    seq = datasets.make_sequence("office", 0, num_frames=distinct, height=height, width=width,
                                 seed=31)
    export.save_scannet(seq, base, overwrite=True)
    rng = np.random.default_rng(0)
    names, lut = datasets.classes.label_space("scannet12")
    pred_dir = os.path.join(root, "base_preds")
    os.makedirs(pred_dir, exist_ok=True)
    k = len(names)
    for t in range(distinct):
      labels = lut[datasets.classes.EMBEDDED_TO_NYU40[np.maximum(seq.labels[t], 0)]]
      onehot = np.eye(k, dtype=np.float32)[np.maximum(labels, 0)]
      noise = rng.dirichlet(np.ones(k), (height, width)).astype(np.float32)
      mean = 0.6 * onehot + 0.4 * noise
      sources.save_prediction(os.path.join(pred_dir, f"{t:06d}.npz"), mean=mean,
                              var=(0.05 * noise).astype(np.float32))
  scene = os.path.join(root, f"scene_{frames}")
  preds = os.path.join(root, f"preds_{frames}", f"scene_{frames}")
  if not os.path.isdir(os.path.join(scene, "pose")):
    for sub, ext in (("color", ".jpg"), ("depth", ".png"), ("label-filt", ".png")):
      os.makedirs(os.path.join(scene, sub), exist_ok=True)
      for i in range(frames):
        os.symlink(os.path.abspath(os.path.join(base, sub, f"{i % distinct}{ext}")),
                   os.path.join(scene, sub, f"{i}{ext}"))
    os.makedirs(os.path.join(scene, "pose"), exist_ok=True)
    os.makedirs(preds, exist_ok=True)
    poses = [np.loadtxt(os.path.join(base, "pose", f"{t}.txt")) for t in range(distinct)]
    for i in range(frames):        # pass after pass through the same room, as a long scan is
      np.savetxt(os.path.join(scene, "pose", f"{i}.txt"), poses[i % distinct], fmt="%.9f")
      os.symlink(os.path.abspath(os.path.join(root, "base_preds", f"{i % distinct:06d}.npz")),
                 os.path.join(preds, f"{i:06d}.npz"))
    os.symlink(os.path.abspath(os.path.join(base, "intrinsic")), os.path.join(scene, "intrinsic"))
  return scene, os.path.dirname(preds)


def _child(mode: str, scene: str, preds: str, betas: int) -> dict:
  """One measurement, in this process: `stream` or `memory`."""
  from jaxfusion.lab import flags  # pylint: disable=import-outside-toplevel
  from jaxfusion.lab import sequences  # pylint: disable=import-outside-toplevel
  from jaxfusion.lab import tuning  # pylint: disable=import-outside-toplevel
  options = sequences.DataOptions(predictions=preds, label_space="scannet12")
  grid = np.linspace(0.0, 1.0, betas)
  spec = f"scannet:{scene}"
  start = time.perf_counter()
  if mode == "stream":
    data, out = tuning.stream_sweep(spec, options, grid)
  else:
    data = tuning.load_data_sequence(spec, options)
    out = tuning.sweep_beta(data["frames"], data["camera"], data["gt"]["coords"],
                            data["gt"]["labels"], betas=grid, capacity=data["capacity"])
  seconds = time.perf_counter() - start
  del flags
  return {"seconds": seconds, "miou": [float(x) for x in out["miou"]],
          "voxels": int(np.max(out["occupied"])),
          "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0}


def _measure(mode: str, scene: str, preds: str, betas: int, frames: int) -> dict:
  cmd = [sys.executable, "-m", "bench.streaming", "--child", mode, scene, preds, str(betas)]
  proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
  if proc.returncode:
    raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
  out = json.loads(proc.stdout.strip().splitlines()[-1])
  out.update(mode=mode, frames=frames, frames_per_s=frames / out["seconds"])
  return out


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(prog="python -m bench.streaming", description=__doc__)
  parser.add_argument("--quick", action="store_true", help="tiny: 24 and 48 frames at 120×160")
  parser.add_argument("--frames", type=int, nargs="+", default=[100, 400, 1600])
  parser.add_argument("--memory-frames", type=int, default=100,
                      help="the in-memory peer's length (it must fit in memory)")
  parser.add_argument("--distinct", type=int, default=40)
  parser.add_argument("--betas", type=int, default=4)
  parser.add_argument("--out", default="bench/results/streaming")
  parser.add_argument("--child", nargs=4, default=None, help=argparse.SUPPRESS)
  args = parser.parse_args(argv)
  if args.child:
    mode, scene, preds, betas = args.child
    print(json.dumps(_child(mode, scene, preds, int(betas))))
    return 0
  height, width = (120, 160) if args.quick else (480, 640)
  lengths = [24, 48] if args.quick else args.frames
  memory_frames = 24 if args.quick else args.memory_frames
  distinct = 8 if args.quick else args.distinct
  root = os.path.join(WORK, f"{height}x{width}")
  rows = []
  for frames in sorted(set(lengths) | {memory_frames}):
    scene, preds = _make(root, distinct, frames, height, width)
    modes = ["stream"] + (["memory"] if frames == memory_frames else [])
    for mode in modes:
      row = _measure(mode, scene, preds, args.betas, frames)
      rows.append(row)
      print(f"{mode:>6} {frames:5d} frames: {row['frames_per_s']:.2f} frames/s, peak RSS "
            f"{row['peak_rss_mib']:.0f} MiB, {row['voxels']} voxels", flush=True)
  previous = os.path.join(args.out, "streaming.json")
  if os.path.isfile(previous) and not args.quick:   # keep the lengths not measured again
    with open(previous, encoding="utf-8") as f:
      old = json.load(f)
    if old.get("size") == [height, width]:
      measured = {(r["mode"], r["frames"]) for r in rows}
      rows = sorted(rows + [r for r in old["rows"] if (r["mode"], r["frames"]) not in measured],
                    key=lambda r: (r["frames"], r["mode"] != "stream"))
      lengths = sorted({r["frames"] for r in rows if r["mode"] == "stream"})
  stream_row = next(r for r in rows if r["mode"] == "stream" and r["frames"] == memory_frames)
  memory_row = next(r for r in rows if r["mode"] == "memory")
  ratio = stream_row["frames_per_s"] / memory_row["frames_per_s"]
  same = stream_row["miou"] == memory_row["miou"]
  os.makedirs(args.out, exist_ok=True)
  record = {"command": "python -m bench.streaming" + (" --quick" if args.quick else
                                                      f" --frames {' '.join(map(str, lengths))}"),
            "size": [height, width], "classes": 12, "betas": args.betas, "rows": rows,
            "throughput_ratio_stream_over_memory": ratio, "same_miou": same}
  with open(os.path.join(args.out, "streaming.json"), "w", encoding="utf-8") as f:
    json.dump(record, f, indent=1)
  lines = [f"# Streaming a long sequence\n\n`{record['command']}`: a {height}×{width} ScanNet-"
           f"format sequence, K = 12 precomputed predictions, a sweep of {args.betas} β "
           "(`jaxfusion sweep --data`), each run in a fresh process.\n",
           "| path | frames | frames/s | peak RSS (MiB) | map voxels |", "|---|---|---|---|---|"]
  lines += [f"| {r['mode']} | {r['frames']} | {r['frames_per_s']:.2f} | "
            f"{r['peak_rss_mib']:.0f} | {r['voxels']} |" for r in rows]
  lines.append(f"\nStreamed / in-memory throughput at {memory_frames} frames: {ratio:.2f} "
               f"(target ≥ 0.8); the same mIoU on every β: {same}.")
  with open(os.path.join(args.out, "streaming.md"), "w", encoding="utf-8") as f:
    f.write("\n".join(lines) + "\n")
  print("\n".join(lines))
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
