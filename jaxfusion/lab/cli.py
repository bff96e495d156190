"""The `jaxfusion` command.

  demo            the paper's experiment on the embedded world, end to end (`lab.demo`)
  figure          the paper's Fig. 2 outlier example as a PNG (`lab.demo`)
  run             fuse one sequence of your data with one rule (`lab.maps`)
  eval            score a saved map against GT voxel labels (`lab.maps`)
  export          export a saved map as a class-coloured PLY (`lab.maps`)
  gt              GT voxel labels of one sequence, from label images or a labelled mesh
                  (`lab.ground_truth`)
  list            list the embedded sequences (`lab.data`)
  render          render an embedded frame as RGB | depth | labels PNG (`lab.data`)
  save            render an embedded sequence to a folder (`lab.data`)
  show            preview a frame of a saved sequence folder (`lab.data`)
  bench           time the embedded world's renderer (`lab.data`)
  view            interactive 3-D viewer of saved maps (`lab.viewer`)
  study           rules × shifts × layouts with bootstrap intervals (`lab.study`)
  mesh-study      meshes vs the true surface: Chamfer, F-score, mesh mIoU (`lab.mesh_study`)
  sweep           one sequence fused with a grid of β in one call (`lab.tuning`)
  tune-beta       fit β by gradient descent on a calibration sequence (`lab.tuning`)
  tune-compare    which tuning objective tracks the mIoU optimum (`lab.tuning`)
  tune-protocol   tune β on calibration layouts, judge on held-out ones (`lab.tuning`)
  simulate-sweep  fusion rules on a grid of a simulated front end (`lab.simulate`)
  learn-rule      fit the learned fusion rule on calibration layouts (`lab.learning`)
  predict         a front end's predictions for sequences, as precomputed files (`lab.predict`)
  changing-world  free-space clearing on moved objects, re-integration after drift
                  (`lab.changing`)

Each command module offers `add_parser(subparsers)` and `main(args) -> int`; shared flags are
in `lab.flags`. Errors a user can fix (a wrong sequence spec, an unreadable folder, an unknown
rule, a mismatched checkpoint or cache) are printed as one line and exit with status 2, without
a traceback. Compiled programs are kept between runs in the user's cache folder
(`lab.compile_cache`; `JAXFUSION_COMPILE_CACHE=off` turns that off), and a command asks Linux
for huge pages for the maps' arrays (`lab.hugepages`; `JAXFUSION_HUGEPAGES=off`).
"""

import argparse
import importlib
import sys

# The modules that register commands, in the order of `jaxfusion --help`.
COMMAND_MODULES = ("demo", "maps", "ground_truth", "data", "viewer.command", "study",
                   "mesh_study", "tuning", "simulate", "learning", "predict", "changing")


def build_parser() -> argparse.ArgumentParser:
  """The `jaxfusion` parser with every command module's subcommands."""
  parser = argparse.ArgumentParser(prog="jaxfusion",
                                   description="Robust Bayesian semantic voxel mapping: the "
                                               "commands of jaxfusion's lab.")
  sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
  for name in COMMAND_MODULES:
    importlib.import_module(f"jaxfusion.lab.{name}").add_parser(sub)
  return parser


def main(argv=None) -> int:
  """Parses `argv` (default `sys.argv[1:]`), runs the command, returns the exit status.

  A command with `--processes N > 1` is started as N joined local processes
  (`lab.processes.launch`); in each of them, and with `--distributed`, the distributed runtime
  is joined first (`jaxfusion.distributed.initialize`). Started as a command (`argv` None), the
  process first re-executes itself once with huge pages for the maps' arrays, where Linux
  offers them (`lab.hugepages`; `JAXFUSION_HUGEPAGES=off` turns that off)."""
  if argv is None:
    from jaxfusion.lab import hugepages   # pylint: disable=import-outside-toplevel
    hugepages.reexec()
  argv = list(sys.argv[1:] if argv is None else argv)
  args = build_parser().parse_args(argv)
  from jaxfusion.lab import compile_cache   # pylint: disable=import-outside-toplevel
  compile_cache.enable()   # compiled programs kept between runs (JAXFUSION_COMPILE_CACHE=off)
  from jaxfusion.lab import processes   # pylint: disable=import-outside-toplevel
  num_processes = getattr(args, "processes", 1)
  if num_processes is not None and num_processes < 1:
    print(f"jaxfusion {args.command}: error: --processes must be ≥ 1; got {num_processes}",
          file=sys.stderr)
    return 2
  if (num_processes or 1) > 1 and not processes.is_worker():
    return processes.launch(argv, num_processes, name=f"jaxfusion {args.command}")
  if processes.is_worker() or getattr(args, "distributed", False):
    from jaxfusion import distributed   # pylint: disable=import-outside-toplevel
    try:
      distributed.initialize(name=f"jaxfusion {args.command}")
    except distributed.DistributedError as e:
      print(f"jaxfusion {args.command}: error: {e}", file=sys.stderr)
      return 2
  try:
    return int(args.func(args) or 0)
  except (ValueError, FileNotFoundError) as e:   # a CheckpointError is a ValueError
    print(f"jaxfusion {args.command}: error: {e}", file=sys.stderr)
    return 2


if __name__ == "__main__":
  sys.exit(main())
