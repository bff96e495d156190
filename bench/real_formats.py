"""Same numbers through the real formats: the study of embedded sequences, and the study of the
same sequences written in ScanNet's layout (`jaxfusion save --format scannet`) and read back
through `scannet:PATH` with the same predictions (`jaxfusion predict`, from the same front-end
cache), per rule.

The two differ only where the formats round: depth in millimetres, colour through JPEG (which
no rule reads: the predictions are precomputed), labels resized to 1296×968 and back.

  python -m bench.real_formats [--quick] [--out bench/results/real_formats]

Writes `real_formats.json` and `real_formats.md` (mIoU per rule for both, and the difference).
"""

import argparse
import json
import os
import time

from jaxfusion.lab import cli

RULES = ("Sum probs", "Sum labels", "Bayesian", "R", "D", "D+R", "Learned", "GLFS", "Oracle")


def _run(argv):
  code = cli.main(argv)
  if code:
    raise SystemExit(f"jaxfusion {' '.join(argv)} failed with status {code}")


def main(argv=None) -> int:
  parser = argparse.ArgumentParser(prog="python -m bench.real_formats", description=__doc__)
  parser.add_argument("--quick", action="store_true", help="one sequence of 8 frames at 48×64")
  parser.add_argument("--out", default="bench/results/real_formats")
  parser.add_argument("--work", default="outputs/real_formats", help="scratch folder")
  args = parser.parse_args(argv)
  frames, height, width = (8, 48, 64) if args.quick else (30, 96, 128)
  units = [("office", 0)] if args.quick else [("office", 0), ("house", 0), ("office", 1)]
  seed, shift = 1, 1.0
  cache = os.path.join(args.work, "cache")
  sizes = ["--frames", str(frames), "--height", str(height), "--width", str(width),
           "--num-samples", "16", "--resamples", "200"]
  start = time.perf_counter()
  envs = sorted({e for e, _ in units})
  trajectories = sorted({t for _, t in units})
  # 1. the study of the embedded sequences (its own grid: envs × trajectories)
  _run(["study", "--layout-seeds", str(seed), "--envs", *envs, "--trajectories",
        *map(str, trajectories), "--shifts", str(shift), "--cache", cache,
        "--out", os.path.join(args.work, "embedded")] + sizes)
  specs = [f"{e}:{t}:s{seed}:shift{shift:g}" for e in envs for t in trajectories]
  # 2. the same front end's predictions (the same cache), written as files
  preds = os.path.join(args.work, "preds")
  _run(["predict", "--data", *specs, "--out", preds, "--cache", cache] + sizes[:-2])
  # 3. the same sequences in ScanNet's layout
  scans = []
  for e in envs:
    for t in trajectories:
      path = os.path.join(args.work, "scans", f"{e}_{t}_test_s{seed}_shift{shift:g}")
      _run(["save", "--format", "scannet", "--env", e, "--trajectory", str(t),
            "--layout-seeds", str(seed), "--shift", str(shift), "--num-frames", str(frames),
            "--height", str(height), "--width", str(width), "--overwrite", "--out", path])
      scans.append(f"scannet:{path}")
  # 4. the study read back through scannet:PATH
  _run(["study", "--data", *scans, "--predictions", preds, "--label-space", "embedded",
        "--out", os.path.join(args.work, "scannet")] + sizes[-2:])
  read = lambda name: json.load(open(os.path.join(args.work, name, "study.json")))["summary"]
  embedded = read("embedded")[f"{shift:g}"]["methods"]
  scannet = read("scannet")["data"]["methods"]
  rows = {r: {"embedded": 100 * embedded[r]["miou"]["estimate"],
              "scannet": 100 * scannet[r]["miou"]["estimate"]} for r in RULES if r in embedded}
  for r in rows.values():
    r["difference"] = r["scannet"] - r["embedded"]
  worst = max(abs(r["difference"]) for r in rows.values())
  os.makedirs(args.out, exist_ok=True)
  record = {"command": "python -m bench.real_formats" + (" --quick" if args.quick else ""),
            "sequences": specs, "frames": frames, "size": [height, width], "rows": rows,
            "max_abs_difference": worst, "seconds": time.perf_counter() - start}
  with open(os.path.join(args.out, "real_formats.json"), "w", encoding="utf-8") as f:
    json.dump(record, f, indent=1)
  lines = [f"# Same numbers through the real formats\n\n`{record['command']}`: "
           f"{len(specs)} sequences ({', '.join(specs)}), {frames} frames at {height}×{width}, "
           "M = 16; the embedded study against the same sequences written in ScanNet's layout and "
           "read back with the same predictions. Pooled mIoU (%).\n",
           "| rule | embedded | through ScanNet's layout | difference |", "|---|---|---|---|"]
  lines += [f"| {r} | {v['embedded']:.2f} | {v['scannet']:.2f} | {v['difference']:+.2f} |"
            for r, v in rows.items()]
  lines.append(f"\nLargest difference: {worst:.2f} points (target: within 0.1).")
  with open(os.path.join(args.out, "real_formats.md"), "w", encoding="utf-8") as f:
    f.write("\n".join(lines) + "\n")
  print("\n".join(lines))
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
