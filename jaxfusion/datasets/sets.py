"""Sets of sequences: one notion for every command that runs on more than one sequence.

A *data set* is a list of sequence specs (`specs`), written on a command line as
`--data SPEC [SPEC ...]`, where each item is

* a spec (`office:0:s1`, `scannet:/data/scans/scene0000_00`, `tum:PATH`, `saved:PATH`);
* a folder pattern (`scannet:/data/scans/scene00*`): every folder that matches, sorted;
* a text file of items, one a line (`#` starts a comment), named by its path (`sets.txt`) or
  `@sets.txt`; its relative folder paths are relative to the file.

The embedded world's layout seeds are one way to name such a set (`embedded_set`): environments
× trajectories × layout seeds × shifts, each an embedded spec with its seed and shift.

A sequence has an *identity* (`identity`): the layout seed of an embedded sequence (another
trajectory or shift of the same layout sees the same room), the real path of a folder. Sets that
calibrate (fit, tune, select) and sets that judge must share none (`check_disjoint`).
"""

import glob
import os
from typing import Iterable, Mapping, Optional, Sequence

from jaxfusion.datasets import specs as specs_lib
from jaxfusion.datasets.specs import SequenceSpec

_PATTERN_CHARS = set("*?[")


def _read_list(path: str) -> list:
  if not os.path.isfile(path):
    raise FileNotFoundError(f"no such list of sequences {path!r}")
  base = os.path.dirname(os.path.abspath(path))
  items = []
  with open(path, encoding="utf-8") as f:
    for line in f:
      line = line.split("#", 1)[0].strip()
      if not line:
        continue
      head, sep, rest = line.partition(":")
      if sep and head in ("scannet", "tum", "saved") and rest and not os.path.isabs(rest):
        line = f"{head}:{os.path.join(base, rest)}"
      items.append(line)
  if not items:
    raise ValueError(f"the list of sequences {path} names none")
  return items


def _is_list_file(item: str) -> bool:
  return item.startswith("@") or (item.endswith(".txt") and ":" not in item)


def expand(items: Iterable[str], *, what: str = "--data") -> list:
  """The specs a list of data items names (see the module docstring), in order.

  Args:
    items: specs, folder patterns and list files.
    what: the flag the items came from, for messages.

  Returns:
    A list of `SequenceSpec`, without repeats.

  Raises:
    ValueError: a bad spec, a pattern that matches no folder, an empty list, a repeat.
    FileNotFoundError: a list file that does not exist.
  """
  out, seen = [], {}
  stack = [(str(item), None) for item in items][::-1]
  if not stack:
    raise ValueError(f"{what} names no sequence")
  while stack:
    item, origin = stack.pop()
    if _is_list_file(item):
      path = item[1:] if item.startswith("@") else item
      stack.extend((x, path) for x in _read_list(path)[::-1])
      continue
    try:
      spec = specs_lib.parse_spec(item)
    except ValueError as e:
      where = f" (in {origin})" if origin else ""
      raise ValueError(f"{what}{where}: {e}") from None
    if spec.path is not None and _PATTERN_CHARS & set(spec.path):
      matches = sorted(p for p in glob.glob(os.path.expanduser(spec.path)) if os.path.isdir(p))
      if not matches:
        raise ValueError(f"{what}: no folder matches {item!r}")
      found = [spec._replace(path=p) for p in matches]
    else:
      found = [spec]
    for s in found:
      key = str(s)
      if key in seen:
        raise ValueError(f"{what} names {key} twice")
      seen[key] = True
      out.append(s)
  return out


def embedded_set(envs: Sequence[str], trajectories: Sequence[int], layout_seeds: Sequence[int],
                 shifts: Sequence[float], *, domain: str = "test") -> list:
  """The embedded sequences of a grid as specs, layout seed by layout seed (then environment,
  trajectory and shift: the order of the study's grid)."""
  return [SequenceSpec("synthetic", env=e, trajectory=int(t), domain=domain,
                       layout_seed=int(s), shift=float(x))
          for s in layout_seeds for e in envs for t in trajectories for x in shifts]


def identity(spec: SequenceSpec) -> tuple:
  """What makes two sequences the same data: the layout seed of an embedded one (default 0),
  a floor's rooms and layout seed, the real path of a folder."""
  if spec.is_embedded:
    return ("embedded layout seed", 0 if spec.layout_seed is None else int(spec.layout_seed))
  if spec.kind == "floor":
    return ("floor", int(spec.rooms), 0 if spec.layout_seed is None else int(spec.layout_seed))
  return ("folder", os.path.realpath(os.path.expanduser(spec.path)))


def check_disjoint(sets: Mapping[str, Optional[Sequence[SequenceSpec]]]) -> None:
  """Refuses sets that share a sequence (`identity`), with one line naming both sets.

  Args:
    sets: name (e.g. "--calibration-data") → specs; None entries are left out.

  Raises:
    ValueError: two sets share a sequence.
  """
  owner = {}
  for name, specs in sets.items():
    for spec in specs or ():
      key = identity(spec)
      if key in owner and owner[key][0] != name:
        other, first = owner[key]
        what = (f"layout seed {key[1]}" if key[0].startswith("embedded") else key[1])
        raise ValueError(f"{other} and {name} share {what} ({first} and {spec}); the sets that "
                         "calibrate and the sets that judge must be disjoint")
      owner.setdefault(key, (name, spec))


def sequence_name(spec: SequenceSpec) -> str:
  """A sequence's name in reports, caches and prediction folders: the folder's own name
  (`scannet:/data/scans/scene0000_00` → `scene0000_00`), or for an embedded sequence
  `ENV_TRAJECTORY_DOMAIN_sSEED_shiftX_CHANGE` (seed, shift and change when the spec names them:
  `office:0:s1:moved` → `office_0_test_s1_moved`, never the name of `office:0:s1`), or for a
  floor `floor_N_DOMAIN_sSEED_shiftX` (`floor:12:s3` → `floor_12_test_s3`)."""
  if spec.kind == "floor":
    name = f"floor_{spec.rooms}_{spec.domain}"
    name += "" if spec.layout_seed is None else f"_s{spec.layout_seed}"
    return name + ("" if spec.shift is None else f"_shift{spec.shift:g}")
  if not spec.is_embedded:
    return os.path.basename(os.path.normpath(spec.path))
  name = f"{spec.env}_{spec.trajectory}_{spec.domain}"
  if spec.layout_seed is not None:
    name += f"_s{spec.layout_seed}"
  if spec.shift is not None:
    name += f"_shift{spec.shift:g}"
  if spec.change is not None:
    name += f"_{spec.change}"
  return name


def predictions_folder(root: str, spec: SequenceSpec) -> str:
  """`ROOT/<sequence_name(spec)>/`, the per-sequence folder of precomputed predictions; for an
  embedded spec, `ROOT/ENV_TRAJECTORY_DOMAIN[_CHANGE]/` (the sequence's own name) when only that
  older name exists — a changing world's never falls back to its static sequence's folder.

  Raises:
    FileNotFoundError: neither folder exists.
  """
  path = os.path.join(root, sequence_name(spec))
  if os.path.isdir(path):
    return path
  if spec.is_embedded:
    change = "" if spec.change is None else f"_{spec.change}"
    older = os.path.join(root, f"{spec.env}_{spec.trajectory}_{spec.domain}{change}")
    if os.path.isdir(older):
      return older
  raise FileNotFoundError(f"--predictions: no folder {path} for {spec} (one folder per "
                          "sequence, named after the sequence's own folder)")
