"""`python -m bench [--quick] [--out DIR]`: runs the benchmark suite and writes results.json,
results.md and scaling.png (default `bench/results/`).

XLA's CPU runtime allocates its temporary buffers with malloc on every call; above glibc's mmap
threshold each allocation is a fresh mapping whose pages fault in again on every frame, which on
a virtual machine costs more than the arithmetic. Unless `--no-malloc-tune` is given (or the
variable is already set), the suite re-executes itself with `MALLOC_MMAP_THRESHOLD_` and
`MALLOC_TRIM_THRESHOLD_` raised so that freed buffers are reused; both settings are recorded in
the results. Users get the same effect by exporting the two variables.
"""

import argparse
import os
import pathlib
import sys

_MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(2**30), "MALLOC_TRIM_THRESHOLD_": str(2**31)}


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.split("\n")[0])
  parser.add_argument("--quick", action="store_true", help="fewer configurations and repeats")
  parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results"),
                      help="output folder")
  parser.add_argument("--no-malloc-tune", action="store_true",
                      help="keep glibc's default malloc thresholds")
  args = parser.parse_args(argv)
  if not args.no_malloc_tune and "MALLOC_MMAP_THRESHOLD_" not in os.environ:
    env = dict(os.environ, **_MALLOC_ENV)
    os.execve(sys.executable, [sys.executable, "-m", "bench", *sys.argv[1:]], env)
  from bench import suite  # pylint: disable=import-outside-toplevel
  config = suite.Config.quick() if args.quick else suite.Config.full()
  suite.run(config, out_dir=args.out, log=lambda s: print(s, flush=True))
  print(f"wrote {args.out}/results.json, results.md, scaling.png")


if __name__ == "__main__":
  main()
