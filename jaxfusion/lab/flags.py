"""Flag groups the commands share: one spelling and one meaning for each.

- `--layout-seeds S [S ...]`: layout seeds of the embedded world (which room, which furniture,
  which path). Older spellings, still accepted where a command had them: `--seeds` (study),
  `--scene-seed` (simulate-sweep), `--seed` (sweep, tune-beta, tune-compare, tune-protocol and
  the datasets commands, where it meant the layout).
- `--mc-seed N`: seed of the front end's randomness (MC-dropout keys, the simulated network's
  draws). Older spelling: `--seed` (run, simulate-sweep, where it meant that).
- `--cache DIR`: the front-end cache folder (`frontend.cached_predictions`). Older spelling:
  `--cache-dir` (the tuning commands).
- `--frames`, `--height`, `--width`, `--num-samples`, `--checkpoint`, `--beta`,
  `--aggregate`, `--voxel-size`, `--envs`, `--trajectories`, `--shifts`: what they say, the
  same in every command.
"""

import argparse
from typing import Optional, Sequence

import jaxfusion as jf
from jaxfusion.datasets import synthetic


def add_layout_seeds(parser: argparse.ArgumentParser, *, default: Optional[Sequence[int]],
                     aliases: Sequence[str] = (), help_suffix: str = "") -> None:
  """`--layout-seeds` (dest `layout_seeds`, a list of ints)."""
  parser.add_argument("--layout-seeds", *aliases, dest="layout_seeds", nargs="+", type=int,
                      default=None if default is None else list(default), metavar="SEED",
                      help="layout seeds of the embedded world" + help_suffix)


def one_layout_seed(args: argparse.Namespace) -> int:
  """The single layout seed of a command that renders one layout."""
  seeds = args.layout_seeds
  if len(seeds) != 1:
    raise ValueError(f"this command renders one layout: give one --layout-seeds value; got "
                     f"{seeds}")
  return int(seeds[0])


def add_mc_seed(parser: argparse.ArgumentParser, *, default: int = 0,
                aliases: Sequence[str] = (), what: str = "the MC-dropout keys") -> None:
  """`--mc-seed` (dest `mc_seed`)."""
  parser.add_argument("--mc-seed", *aliases, dest="mc_seed", type=int, default=default,
                      help=f"seed of {what} (default {default})")


def add_cache(parser: argparse.ArgumentParser, *, default: Optional[str],
              aliases: Sequence[str] = ()) -> None:
  """`--cache` (dest `cache`): the front-end cache folder."""
  where = "OUT/cache" if default is None else default
  parser.add_argument("--cache", *aliases, dest="cache", default=default, metavar="DIR",
                      help=f"front-end cache folder (default {where}; shareable between "
                           "demo, study and the tuning commands)")


def add_sizes(parser: argparse.ArgumentParser, *, frames: Optional[int],
              height: Optional[int], width: Optional[int],
              num_samples: Optional[int] = None, samples: bool = True) -> None:
  """`--frames`, `--height`, `--width` and (with `samples`) `--num-samples`."""
  parser.add_argument("--frames", type=int, default=frames, help="frames per sequence")
  parser.add_argument("--height", type=int, default=height, help="image rows")
  parser.add_argument("--width", type=int, default=width, help="image columns")
  if samples:
    parser.add_argument("--num-samples", type=int, default=num_samples,
                        help="MC-dropout samples M")


def check_at_least(args: argparse.Namespace, low: int = 1,
                   names: Sequence[str] = ("frames", "height", "width", "num_samples")) -> None:
  """Raises ValueError naming the flag when a given size is below `low`."""
  for name in names:
    value = getattr(args, name, None)
    if value is not None and value < low:
      raise ValueError(f"--{name.replace('_', '-')} must be at least {low}")


def add_checkpoint(parser: argparse.ArgumentParser) -> None:
  """`--checkpoint`: network weights (default: the shipped ones)."""
  parser.add_argument("--checkpoint", default=None,
                      help="network weights (default: the shipped ones)")


def add_fusion(parser: argparse.ArgumentParser, *, beta: Optional[float] = 0.3,
               aggregate: Optional[str] = "sum", voxel_size: Optional[float] = 0.1,
               voxels: bool = True) -> None:
  """`--beta`, `--aggregate` and (with `voxels`) `--voxel-size`."""
  parser.add_argument("--beta", type=float, default=beta, help="β of R and D+R")
  parser.add_argument("--aggregate", choices=("sum", "mean"), default=aggregate,
                      help="a voxel's pixels in one frame: summed (the paper) or one mean "
                           "observation")
  if voxels:
    parser.add_argument("--voxel-size", type=float, default=voxel_size,
                        help="voxel edge in metres")


def add_geometry(parser: argparse.ArgumentParser) -> None:
  """`--geometry-voxel-size`, `--truncation`, `--no-geometry`: the map's TSDF layer."""
  parser.add_argument("--geometry-voxel-size", type=float, default=0.05,
                      help="voxel edge of the geometry layer (TSDF) in metres")
  parser.add_argument("--truncation", type=float, default=4.0,
                      help="TSDF truncation τ in geometry voxels")
  parser.add_argument("--no-geometry", action="store_true",
                      help="semantics only: no TSDF layer and no mesh")


def geometry_config(args):
  """The TSDFConfig of `add_geometry`'s flags (None with --no-geometry)."""
  if getattr(args, "no_geometry", False):
    return None
  return jf.tsdf.TSDFConfig(voxel_size=args.geometry_voxel_size,
                            truncation_voxels=args.truncation)


def add_grid(parser: argparse.ArgumentParser, *, envs: Optional[Sequence[str]],
             trajectories: Optional[Sequence[int]], shifts: bool = False) -> None:
  """`--envs`, `--trajectories` and (with `shifts`) `--shifts`."""
  parser.add_argument("--envs", nargs="+", choices=synthetic.ENVIRONMENTS,
                      default=None if envs is None else list(envs))
  parser.add_argument("--trajectories", nargs="+", type=int,
                      choices=range(synthetic.NUM_TRAJECTORIES),
                      default=None if trajectories is None else list(trajectories))
  if shifts:
    parser.add_argument("--shifts", nargs="+", type=float, default=None,
                        help="test-domain shifts in [0, 1]")


def as_tuple(value):
  """A list from argparse as a tuple (None stays None)."""
  return None if value is None else tuple(value)


def add_learned_rule(parser: argparse.ArgumentParser) -> None:
  """`--learned-rule PARAMS_JSON` | `--no-learned-rule`: the learned rule as a seventh row."""
  learned = parser.add_mutually_exclusive_group()
  learned.add_argument("--learned-rule", default=None, metavar="PARAMS_JSON",
                       help="params.json of `jaxfusion learn-rule`, fused as a seventh row "
                            "(default: the shipped parameters, jaxfusion_models."
                            "LEARNED_RULE_PATH)")
  learned.add_argument("--no-learned-rule", action="store_true",
                       help="the six paper rules only")


def learned_rule(args: argparse.Namespace) -> tuple:
  """`(params, source)` of `add_learned_rule`'s flags: the parameters (`learn.load_params`) and
  the path they came from, or `(None, None)` with --no-learned-rule."""
  if args.no_learned_rule:
    return None, None
  from jaxfusion import learn   # pylint: disable=import-outside-toplevel
  if args.learned_rule is None:
    import jaxfusion_models  # pylint: disable=import-outside-toplevel
    source = str(jaxfusion_models.LEARNED_RULE_PATH)
  else:
    source = args.learned_rule
  return learn.load_params(source), source


def add_glfs_rule(parser: argparse.ArgumentParser) -> None:
  """`--glfs PARAMS_JSON` | `--no-glfs`: GLFS (docs/equations.md §3.10) as a row."""
  group = parser.add_mutually_exclusive_group()
  group.add_argument("--glfs", default=None, metavar="PARAMS_JSON",
                     help="params.json of `jaxfusion learn-rule --family glfs`, fused as a row "
                          "(default: the shipped table, jaxfusion_models.GLFS_PATH)")
  group.add_argument("--no-glfs", action="store_true", help="no GLFS row")


def glfs_rule(args: argparse.Namespace) -> tuple:
  """`(params, source)` of `add_glfs_rule`'s flags, or `(None, None)` with --no-glfs."""
  if args.no_glfs:
    return None, None
  from jaxfusion import learn   # pylint: disable=import-outside-toplevel
  if args.glfs is None:
    import jaxfusion_models  # pylint: disable=import-outside-toplevel
    source = str(jaxfusion_models.GLFS_PATH)
  else:
    source = args.glfs
  family, params = learn.load_rule(source)
  if family != "glfs":
    raise ValueError(f"--glfs {source}: a {family!r} parameter file, not a GLFS table")
  return params, source


def learned_variants(args: argparse.Namespace) -> tuple:
  """`((tag, params), …)` of repeated `--variant TAG=PARAMS_JSON` flags: learned rules as
  `(tag, params)`, members of the rule family (docs/equations.md §3.11) as
  `(tag, params, "family")`."""
  from jaxfusion import learn   # pylint: disable=import-outside-toplevel
  out = []
  for spec in getattr(args, "variant", []) or []:
    tag, sep, path = spec.partition("=")
    if not sep or not tag or not path:
      raise ValueError(f"--variant takes TAG=PARAMS_JSON; got {spec!r}")
    family, params = learn.load_rule(path)
    if family not in ("learned", "family"):
      raise ValueError(f"--variant {spec}: a {family!r} parameter file, not a learned rule or "
                       f"a member of the rule family (give GLFS with --glfs)")
    out.append((tag, params) if family == "learned" else (tag, params, family))
  tags = [v[0] for v in out]
  if len(set(tags)) != len(tags):
    raise ValueError(f"--variant tags must differ; got {tags}")
  return tuple(out)


def variant_family(variant: tuple) -> str:
  """The rule family of a `learned_variants` entry: "learned" or "family"."""
  return variant[2] if len(variant) > 2 else "learned"


def add_study_run(parser: argparse.ArgumentParser, *, seed_aliases: Sequence[str] = (),
                  seeds_help: str = "") -> None:
  """The flags of a study's grid of runs (`jaxfusion study`, `jaxfusion mesh-study`): cache,
  checkpoint, layout seeds, environments, trajectories, shifts, sizes, β and aggregation, the
  MC seed, bootstrap resamples and the learned rule."""
  add_cache(parser, default=None)
  add_checkpoint(parser)
  add_layout_seeds(parser, default=None, aliases=seed_aliases, help_suffix=seeds_help)
  add_grid(parser, envs=None, trajectories=None, shifts=True)
  add_sizes(parser, frames=None, height=None, width=None)
  add_fusion(parser, beta=None, aggregate=None, voxels=False)
  add_mc_seed(parser)
  parser.add_argument("--resamples", type=int, default=None, help="bootstrap resamples")
  add_learned_rule(parser)


# --- several processes (jaxfusion.distributed, lab.processes) ---------------------------------
def add_processes(parser: argparse.ArgumentParser) -> None:
  """`--processes N` (start N joined local processes; `cli.main` launches them) and
  `--distributed` (join a cluster's processes, `jax.distributed.initialize()` from the
  scheduler's environment, e.g. under `srun`)."""
  parser.add_argument("--processes", type=int, default=1, metavar="N",
                      help="run as N processes on this machine, joined by JAX's distributed "
                           "runtime (a coordinator on 127.0.0.1); each takes its share and "
                           "process 0 writes the outputs, identical to one process's")
  parser.add_argument("--distributed", action="store_true",
                      help="join the processes a cluster scheduler started (SLURM, Open MPI, "
                           "...: jax.distributed.initialize() reads its environment)")


# --- your data: one set of flags for every command that runs on sequences ---------------------
def add_data(parser: argparse.ArgumentParser, *, calibration: bool = False,
             validation: bool = False, required: bool = False,
             predictions: bool = True) -> None:
  """`--data SPEC [SPEC ...]` (the sequences, `datasets.sets.expand`) and, with `calibration` /
  `validation`, `--calibration-data` / `--validation-data` the same way; `--stride`,
  `--label-space`, `--class-map`, `--unmapped` and (with `predictions`) `--predictions ROOT`
  and `--missing-predictions`."""
  what = ("sequences: specs (office:0:s1, scannet:PATH, tum:PATH, saved:PATH), folder "
          "patterns (scannet:/data/scans/scene00*) or text files of specs (@list.txt)")
  parser.add_argument("--data", nargs="+", default=None, required=required, metavar="SPEC",
                      help=what + "; default: the command's layout seeds of the embedded world")
  if calibration:
    parser.add_argument("--calibration-data", nargs="+", default=None, metavar="SPEC",
                        help="the sequences to fit on, named as --data (disjoint from the "
                             "judged ones)")
  if validation:
    parser.add_argument("--validation-data", nargs="+", default=None, metavar="SPEC",
                        help="the sequences to select on, named as --data (disjoint from the "
                             "others)")
  parser.add_argument("--stride", type=int, default=1,
                      help="keep every N-th frame of a folder (default 1)")
  if predictions:
    parser.add_argument("--predictions", default=None, metavar="ROOT",
                        help="precomputed predictions: one folder per sequence, named after "
                             "the sequence's own folder (ROOT/scene0000_00/), of per-frame "
                             ".npz files (mean, var or samples; det optional); default: the "
                             "front end")
    parser.add_argument("--missing-predictions", choices=("error", "skip"), default="error",
                        help="a frame without a prediction file: an error (default) or "
                             "skipped and counted")
  add_label_space(parser)


def add_label_space(parser: argparse.ArgumentParser) -> None:
  """`--label-space`, `--class-map`, `--unmapped`: the GT's classes and the predictions' map
  onto them, declared once."""
  from jaxfusion.datasets import classes  # pylint: disable=import-outside-toplevel
  parser.add_argument("--label-space", choices=tuple(classes.LABEL_SPACES), default=None,
                      help="the classes a ScanNet folder's NYU40 GT is read into (default "
                           "scannet12, the paper's; embedded: the embedded world's 7)")
  parser.add_argument("--label-tsv", default=None, metavar="TSV",
                      help="ScanNet's scannetv2-labels.combined.tsv, when label-filt/ holds raw "
                           "ScanNet ids (ScanNet's own 2D label exports) rather than NYU40 ids")
  parser.add_argument("--class-map", default=None, metavar="FILE",
                      help="remap the network's classes to the map's before fusion: a .json or "
                           ".csv file (network class → map class; jaxfusion.classmap has the "
                           "format) or a shipped map: " + ", ".join(classes.CLASS_MAPS))
  parser.add_argument("--unmapped", choices=("other", "drop"), default=None,
                      help="with --class-map: classes with no target go to the 'other' class or "
                           "are dropped and the rest renormalised (default: the file's choice, "
                           "else 'other' when the map has an 'other' class)")


def class_map(args: argparse.Namespace):
  """The `--class-map` (a file, or the name of a shipped one), or None."""
  import os  # pylint: disable=import-outside-toplevel
  from jaxfusion.datasets import classes  # pylint: disable=import-outside-toplevel
  path = getattr(args, "class_map", None)
  if not path:
    return None
  if not os.path.exists(path) and path in classes.CLASS_MAPS:
    path = classes.class_map_path(path)
  elif not os.path.exists(path):
    raise FileNotFoundError(f"--class-map: no such file {path!r} (the shipped maps: "
                            f"{', '.join(classes.CLASS_MAPS)})")
  try:
    return jf.ClassMap.from_file(path, unmapped=args.unmapped)
  except ValueError as e:
    raise ValueError(f"--class-map {e}") from None


def data_sets(args: argparse.Namespace, *names: str) -> dict:
  """`{flag: [SequenceSpec] or None}` of the data flags `names` (e.g. "data",
  "calibration_data"), expanded, and refused in one line when two of them share a sequence."""
  from jaxfusion.datasets import sets  # pylint: disable=import-outside-toplevel
  out = {}
  for name in names:
    items = getattr(args, name, None)
    flag = "--" + name.replace("_", "-")
    out[flag] = None if items is None else sets.expand(items, what=flag)
  sets.check_disjoint(out)
  return out


def data_options(args: argparse.Namespace, **defaults):
  """The `lab.sequences.DataOptions` of the shared flags (sizes, stride, predictions, label
  space, class map, voxel size, M, MC seed, cache); `defaults` fill the flags left unset
  (e.g. the command's embedded sizes). `--frames` limits a folder's frames only when given."""
  from jaxfusion.lab import sequences  # pylint: disable=import-outside-toplevel
  values = dict(
      num_frames=getattr(args, "frames", None), max_frames=getattr(args, "frames", None),
      height=getattr(args, "height", None),
      width=getattr(args, "width", None), stride=getattr(args, "stride", 1),
      predictions=getattr(args, "predictions", None),
      missing=getattr(args, "missing_predictions", "error"),
      label_space=getattr(args, "label_space", None),
      label_tsv=getattr(args, "label_tsv", None), class_map=class_map(args),
      voxel_size=getattr(args, "voxel_size", None), num_samples=getattr(args, "num_samples", None),
      mc_seed=getattr(args, "mc_seed", None), cache_dir=getattr(args, "cache", None))
  for key, value in defaults.items():
    if values.get(key) is None:
      values[key] = value
  return sequences.DataOptions(**{k: v for k, v in values.items() if v is not None}).validate()


def run_data_options(args: argparse.Namespace, run):
  """`data_options` whose unset sizes, M, MC seed, layout seed and shift are a study's run's
  (`config.RunConfig`): what `study --data` and `mesh-study --data` read embedded specs with."""
  return data_options(args, num_frames=run.num_frames, height=run.height, width=run.width,
                      num_samples=run.num_samples, mc_seed=run.mc_seed,
                      layout_seed=run.layout_seeds[0], shift=run.shifts[-1])


# --- every rule by one name --------------------------------------------------------------------
RULE_NAMES_HELP = ("sum_probs, sum_labels, bayes, R, D, D+R, learned (the shipped learned rule), "
                   "glfs (the shipped GLFS table), family (the rule family's shipped fit) or a "
                   "params.json of `jaxfusion learn-rule`")


def resolve_rule(name: str, *, beta: Optional[float] = None, aggregate: str = "sum",
                 num_classes: Optional[int] = None) -> tuple:
  """`(key, FusionRule, reads_moments)` of any rule a command can name.

  Args:
    name: a paper rule (`rules.by_name`), "learned" / "glfs" / "family" (the shipped
      parameters: the first learned rule, GLFS, the rule family's fit), or the path of a
      `learn-rule` params.json (any family).
    beta: β of R and D+R (None: the rule's default).
    aggregate: pixel aggregation.
    num_classes: K of the data, checked against a fitted rule's parameters.

  Returns:
    The rule's key (a paper rule's, "learned", "glfs" or the file's family), the rule, and
    whether it is fused on the MC moments (robust and fitted rules) rather than a dropout-off
    pass.

  Raises:
    ValueError: an unknown name, or fitted parameters for another number of classes.
  """
  import os  # pylint: disable=import-outside-toplevel
  from jaxfusion import learn  # pylint: disable=import-outside-toplevel
  from jaxfusion.lab import config as config_lib  # pylint: disable=import-outside-toplevel
  lowered = name.lower()
  source = None
  if lowered in ("learned", "glfs", "family"):
    import jaxfusion_models  # pylint: disable=import-outside-toplevel
    source = str({"learned": jaxfusion_models.LEARNED_RULE_PATH,
                  "glfs": jaxfusion_models.GLFS_PATH,
                  "family": jaxfusion_models.FAMILY_RULE_PATH}[lowered])
  elif name.endswith(".json") or os.path.isfile(name):
    if not os.path.isfile(name):
      raise FileNotFoundError(f"--rule: no such parameter file {name!r}")
    source = name
  if source is not None:
    family, params = learn.load_rule(source, aggregate=aggregate)
    k = None if num_classes is None else fitted_for_other(family, params, num_classes)
    if k is not None:
      raise ValueError(f"--rule {name}: its parameters are fitted for {k} classes, the data has "
                       f"{num_classes}; fit it for these classes with `jaxfusion learn-rule "
                       "--data ...`")
    return family, learn.rule_of(family, params, aggregate=aggregate), True
  kwargs = {"aggregate": aggregate}
  try:
    key = jf.rules.by_name(name).name
  except ValueError:
    raise ValueError(f"--rule: unknown rule {name!r}; choose one of: {RULE_NAMES_HELP}"
                     ) from None
  if key in config_lib.ROBUST_RULES and beta is not None:
    kwargs["beta"] = beta
  return key, jf.rules.by_name(name, **kwargs), key in config_lib.ROBUST_RULES


def fitted_for_other(family: str, params: dict, num_classes: int) -> Optional[int]:
  """The K a fitted rule's parameters are for when it is not `num_classes`, else None (also
  when no parameter depends on K)."""
  k = fitted_num_classes(family, params)
  return k if k is not None and k != num_classes else None


def fitted_num_classes(family: str, params: dict) -> Optional[int]:
  """K a fitted rule's parameters are for (None when no parameter depends on K): GLFS's table
  rows; the learned rule's per-class β, θ, b or context weights."""
  import numpy as np  # pylint: disable=import-outside-toplevel
  if family in ("glfs", "family") and "table" in params:
    return int(np.shape(params["table"])[0])
  for key, per_class_ndim in (("beta", 1), ("bias", 1), ("theta", 2), ("context_theta", 2),
                              ("moment_weights", 2), ("context_weights", 2)):
    value = params.get(key)
    if value is not None and np.ndim(value) == per_class_ndim:
      return int(np.shape(value)[0])
  return None
