"""`python -m bench [--quick] [--out DIR]`: runs the benchmark suite and writes results.json,
results.md and scaling.png (default `bench/results/`).
"""

import argparse
import pathlib


def main(argv=None) -> None:
  parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__.split("\n")[0])
  parser.add_argument("--quick", action="store_true", help="fewer configurations and repeats")
  parser.add_argument("--out", default=str(pathlib.Path(__file__).parent / "results"),
                      help="output folder")
  args = parser.parse_args(argv)
  from bench import suite  # pylint: disable=import-outside-toplevel
  config = suite.Config.quick() if args.quick else suite.Config.full()
  suite.run(config, out_dir=args.out, log=lambda s: print(s, flush=True))
  print(f"wrote {args.out}/results.json, results.md, scaling.png")


if __name__ == "__main__":
  main()
