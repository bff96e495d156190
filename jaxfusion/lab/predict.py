"""`jaxfusion predict`: a front end's per-pixel predictions for a set of sequences, written in the
precomputed format every command reads (`--predictions ROOT`).

For each sequence of `--data`, `ROOT/<sequence name>/<frame id>.npz` holds `mean` and `var`
(the MC-dropout moments, `(H, W, K) float32`) and `det` (one dropout-off pass, which the
baseline rules read); the frame id is ScanNet's frame number, or the frame's index in a saved or
embedded sequence (`lab.sequences`). An embedded sequence's predictions come from the front-end
cache the study uses, so a study on the files reproduces the study on the embedded world.
"""

import argparse
import os

import numpy as np
from tqdm.auto import tqdm

from jaxfusion import io
from jaxfusion.datasets import sets
from jaxfusion.lab import flags
from jaxfusion.lab import frontend
from jaxfusion.lab import sequences


def write_predictions(root: str, item: sequences.Loaded) -> str:
  """Writes one loaded sequence's predictions under `root`; returns its folder."""
  folder = os.path.join(root, item.name)
  os.makedirs(folder, exist_ok=True)
  ids = item.sequence.info.get("frame_ids") or list(range(len(item.sequence)))
  preds = item.predictions
  for t, fid in enumerate(ids):
    arrays = {"mean": preds["mean"][t], "det": preds["det"][t]}
    if preds["var"] is not None:
      arrays["var"] = preds["var"][t]
    io.save_npz(os.path.join(folder, f"{int(fid):06d}.npz"),
                {k: np.asarray(v, np.float32) for k, v in arrays.items()})
  return folder


def add_parser(subparsers) -> None:
  """Adds `predict`."""
  p = subparsers.add_parser(
      "predict", help="write a front end's predictions for sequences in the precomputed format "
                      "(--predictions ROOT of every command)")
  flags.add_data(p, required=True, predictions=False)
  p.add_argument("--out", required=True, metavar="ROOT", help="one folder per sequence here")
  flags.add_checkpoint(p)
  flags.add_sizes(p, frames=None, height=96, width=128, num_samples=16)
  flags.add_layout_seeds(p, default=[1], help_suffix=" of specs that name none (default 1)")
  p.add_argument("--shift", type=float, default=1.0,
                 help="domain shift of embedded specs that name none (default 1)")
  flags.add_mc_seed(p)
  flags.add_cache(p, default=None)
  p.set_defaults(func=main)


def main(args: argparse.Namespace) -> int:
  """Runs `jaxfusion predict`."""
  specs = flags.data_sets(args, "data")["--data"]
  options = flags.data_options(args, num_frames=30, layout_seed=flags.one_layout_seed(args),
                               shift=args.shift,
                               cache_dir=args.cache or os.path.join(args.out, "cache"))
  front_end = frontend.FrontEnd(args.checkpoint, class_names=None)
  for spec in tqdm(specs, desc="predict"):
    item = sequences.load(spec, options, front_end=front_end, gt=False)
    folder = write_predictions(args.out, item)
    tqdm.write(f"{sets.sequence_name(item.spec)}: {len(item.sequence)} frames, "
               f"K = {item.predictions['mean'].shape[-1]} → {folder}")
  return 0
