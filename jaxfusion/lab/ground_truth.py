"""`jaxfusion gt`: ground-truth voxel labels of one sequence of your data, as a file that
`jaxfusion eval --gt` reads.

Examples:
  jaxfusion gt --data office:0 --frames 40 --out gt.npz
  jaxfusion gt --data scannet:/data/scans/scene0000_00 --label-space scannet20 --out gt.npz
  jaxfusion eval --map outputs/run/scene0000_00_robust_dr.npz --gt gt.npz

The GT comes from the data's label images (`datasets.ground_truth.gt_voxel_labels`: the
majority of the labelled pixels per voxel) or, for a ScanNet folder holding its labelled mesh
`<scene>_vh_clean_2.labels.ply`, from the mesh (`gt_from_mesh`: the majority of even surface
samples per voxel); docs/equations.md §7.1–§7.2. The file holds `coords (N, 3) int32`,
`labels (N,) int32`, `hits (N,) int32`, `class_names (K,)` strings, `source` ("images" or
"mesh") and `voxel_size`.
"""

import argparse
import dataclasses
import os
from typing import Optional

import numpy as np

from jaxfusion import datasets
from jaxfusion import io
from jaxfusion.datasets import classes
from jaxfusion.datasets import ground_truth as gt_lib
from jaxfusion.datasets import plyfile
from jaxfusion.datasets import stream
from jaxfusion.datasets import surfaces
from jaxfusion.lab import flags

SOURCES = ("auto", "images", "mesh")
MESH_PATTERN = "*" + surfaces.MESH_SUFFIX


def find_labelled_mesh(folder: str) -> Optional[str]:
  """The folder's labelled GT mesh (`surfaces.labelled_mesh_path`), or None."""
  return surfaces.labelled_mesh_path(folder)


def _nyu40_ids(class_names) -> Optional[np.ndarray]:
  """`(K,) int32` NYU40 id of each class of a label space whose classes map one to one onto
  NYU40 ids (embedded, nyu40, scannet20), else None."""
  names = tuple(class_names)
  if names == tuple(classes.CLASS_NAMES):
    return classes.EMBEDDED_TO_NYU40
  if names == tuple(classes.NYU40_CLASS_NAMES[1:]):
    return np.arange(1, 41, dtype=np.int32)
  if names == tuple(classes.SCANNET20_CLASS_NAMES):
    return np.array([nyu_id for nyu_id, _ in classes.SCANNET20_TABLE], np.int32)
  return None


def _relabel(seq, space: str):
  """The sequence with its GT read into label space `space` through the NYU40 ids of its own
  classes."""
  names, lut = classes.label_space(space)
  if tuple(names) == tuple(seq.class_names):
    return seq
  ids = _nyu40_ids(seq.class_names)
  if ids is None:
    raise ValueError(f"--label-space {space}: the data's classes {list(seq.class_names)} do "
                     "not map onto NYU40 ids; leave --label-space out to keep them")
  labels = None
  if seq.labels is not None:
    ok = (seq.labels >= 0) & (seq.labels < len(ids))
    labels = np.where(ok, lut[ids[np.where(ok, seq.labels, 0)]], classes.IGNORE_LABEL)
  return dataclasses.replace(seq, class_names=names, labels=labels)


def _images(spec, args, space: Optional[str]):
  """`(gt dict, class names)` from the label images of the sequence a spec names."""
  if spec.kind == "scannet":        # read a chunk at a time: a long scan never held whole
    frames = stream.open_stream(spec, stride=args.stride, num_frames=args.frames,
                                label_space=space or "scannet12",
                                label_tsv=getattr(args, "label_tsv", None))
    first = frames.first()
    if first.labels is None:
      raise ValueError(f"{spec}: the data has no ground-truth labels (no label-filt/ folder "
                       f"and no {MESH_PATTERN})")
    gt = gt_lib.gt_from_frames(map(gt_lib.gt_part, frames.chunks(16)), camera=first.camera,
                               num_classes=len(first.class_names), voxel_size=args.voxel_size)
    return gt, first.class_names
  seq = datasets.load_spec(spec, num_frames=args.frames, height=args.height,
                           width=args.width, layout_seed=flags.one_layout_seed(args),
                           stride=args.stride)
  if space is not None:
    seq = _relabel(seq, space)
  if seq.labels is None:
    raise ValueError(f"{spec}: the data has no ground-truth labels")
  return gt_lib.gt_voxel_labels(seq, voxel_size=args.voxel_size), seq.class_names


def ground_truth(args: argparse.Namespace) -> dict:
  """The GT voxel labels `jaxfusion gt` writes.

  Returns:
    dict with `coords (N, 3) int32`, `labels (N,) int32`, `hits (N,) int32`,
    `class_names (K,) str`, `source` ("images" | "mesh") and `voxel_size`.

  Raises:
    ValueError: a bad spec, an unknown label space, no labels, no mesh for `--source mesh`.
    FileNotFoundError: a folder that does not exist.
  """
  try:
    spec = datasets.parse_spec(args.data)
  except ValueError as e:
    raise ValueError(f"--data: {e}") from None
  if args.label_space is not None:
    classes.label_space(args.label_space)              # an unknown one: ValueError naming all
  if not args.voxel_size > 0:
    raise ValueError(f"--voxel-size must be positive; got {args.voxel_size}")
  flags.check_at_least(args, names=("frames", "height", "width", "stride"))
  mesh = None
  if args.source != "images":
    if spec.kind == "scannet":
      if not os.path.isdir(spec.path):
        raise FileNotFoundError(f"scannet: no such folder {spec.path!r}")
      mesh = find_labelled_mesh(spec.path)
    if mesh is None and args.source == "mesh":
      where = spec.path if spec.kind == "scannet" else "the data (a scannet:PATH folder)"
      raise ValueError(f"--source mesh: no {MESH_PATTERN} in {where}")
  if mesh is not None:
    space = args.label_space or "scannet12"
    names, lut = classes.label_space(space)
    m = plyfile.read_labelled_mesh(mesh)
    gt = gt_lib.gt_from_mesh(m["vertices"], m["faces"], m["labels"], lut=lut,
                             voxel_size=args.voxel_size)
    source = "mesh"
  else:
    gt, names = _images(spec, args, args.label_space)
    source = "images"
  return dict(gt, class_names=np.array(names, dtype=str), source=np.array(source),
              voxel_size=np.array(args.voxel_size, np.float64))


def main(args: argparse.Namespace) -> int:
  """Runs `jaxfusion gt`: writes the GT voxel labels of one sequence."""
  out = ground_truth(args)
  io.save_npz(args.out, out)
  print(f"GT: {len(out['coords'])} voxels, {len(out['class_names'])} classes, from "
        f"{out['source']} → {args.out}")
  return 0


def add_parser(subparsers) -> None:
  """Adds `gt`."""
  p = subparsers.add_parser("gt", help="GT voxel labels of one sequence of your data (for eval)")
  p.add_argument("--data", required=True,
                 help="the sequence: ENV:TRAJECTORY (e.g. office:0), scannet:PATH, tum:PATH or "
                      "saved:PATH")
  p.add_argument("--out", default="gt.npz", help="the GT file (.npz)")
  p.add_argument("--voxel-size", type=float, default=0.1,
                 help="voxel edge in metres (the maps' you evaluate)")
  p.add_argument("--source", choices=SOURCES, default="auto",
                 help=f"label images or a ScanNet folder's labelled mesh ({MESH_PATTERN}); "
                      "auto: the mesh when the folder has one")
  p.add_argument("--label-space", default=None, metavar="SPACE",
                 help="the classes of the GT: " + ", ".join(classes.LABEL_SPACES)
                      + " (default: scannet12 for ScanNet, the data's own classes otherwise)")
  p.add_argument("--label-tsv", default=None, metavar="TSV",
                 help="ScanNet's scannetv2-labels.combined.tsv, when label-filt/ holds raw "
                      "ScanNet ids rather than NYU40 ids")
  p.add_argument("--frames", type=int, default=None,
                 help="frames of an embedded sequence (default 60) / the most frames read "
                      "from a folder (default all)")
  p.add_argument("--stride", type=int, default=1, help="keep every N-th frame (folders)")
  p.add_argument("--height", type=int, default=120, help="image rows (embedded sequences)")
  p.add_argument("--width", type=int, default=160, help="image columns (embedded sequences)")
  flags.add_layout_seeds(p, default=[0], help_suffix=" (one; default 0)")
  p.set_defaults(func=main)
