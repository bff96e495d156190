"""One way to name a sequence, and one loader for every kind.

A sequence spec is a short string:

* `office:0` — an embedded sequence, `ENV:TRAJECTORY` (test domain); `office:0:train` for the
  training domain. ENV is `office` or `house`, TRAJECTORY 0, 1 or 2. A layout seed and a
  domain shift may follow, in any order after the trajectory: `office:0:s1` (layout seed 1),
  `office:0:s1:shift0.5`, `house:2:train:s11`; without them the command's own seed and shift
  apply (`load_spec`'s `layout_seed`, `shift`). One change of the world may follow too, in
  any place of that tail (`changes.CHANGES`): `office:0:moved` (objects moved between two
  passes), `office:0:final` (both passes in the final room), `office:0:s2:drift:shift0.5`
  (drifting odometry poses); see `changes.make_changing_sequence`.
* `floor:N` — an embedded floor of N rooms (1–100) joined by corridors, walked through by a
  camera that enters every room (`floor.FloorWalk`; thousands of frames, rendered on demand).
  A domain, a layout seed and a shift may follow, as for an embedded sequence: `floor:12:s3`,
  `floor:12:train:shift0.5`; no change of the world.
* `scannet:PATH` — an exported ScanNet scene folder (`load_scannet`).
* `tum:PATH` — a TUM RGB-D sequence folder (`load_tum`).
* `saved:PATH` — a folder written by `RGBDSequence.save` (`load_sequence`).

The older spelling `synthetic:ENV/TRAJECTORY[/DOMAIN]` is still read.

An embedded sequence is named `f"{env}_{trajectory}_{domain}"` (`make_sequence`), or
`f"{env}_{trajectory}_{domain}_{change}"` with a change; a sequence rendered for one layout
seed is the *unit* `f"{name}_s{seed}"` (`unit_name`), the name reports and caches use.
"""

import dataclasses
import os
from typing import NamedTuple, Optional

from jaxfusion.datasets import changes
from jaxfusion.datasets import floor
from jaxfusion.datasets import scannet
from jaxfusion.datasets import synthetic
from jaxfusion.datasets import tum
from jaxfusion.datasets.sequence import RGBDSequence

KINDS = ("synthetic", "floor", "scannet", "tum", "saved")
DOMAINS = ("test", "train")


class SequenceSpec(NamedTuple):
  """A parsed sequence spec.

  Attributes:
    kind: one of `KINDS`.
    env: environment of an embedded sequence (None otherwise).
    trajectory: trajectory index of an embedded sequence (None otherwise).
    domain: "test" or "train" appearance of an embedded sequence (None otherwise).
    path: the folder of a ScanNet, TUM or saved sequence (None for an embedded one).
    layout_seed: the embedded layout seed the spec names (None: the command's).
    shift: the embedded domain shift the spec names (None: the command's).
    change: the change of an embedded world (`changes.CHANGES`: "moved", "final", "drift")
      or None for the static one.
    rooms: the number of rooms of a floor (None otherwise). A floor is not `is_embedded`
      (it has no ENV:TRAJECTORY) but `is_rendered`: it takes a domain, seed and shift too.
  """
  kind: str
  env: Optional[str] = None
  trajectory: Optional[int] = None
  domain: Optional[str] = None
  path: Optional[str] = None
  layout_seed: Optional[int] = None
  shift: Optional[float] = None
  change: Optional[str] = None
  rooms: Optional[int] = None

  def __str__(self) -> str:
    if self.kind == "floor":
      tail = "" if self.domain == "test" else f":{self.domain}"
      tail += "" if self.layout_seed is None else f":s{self.layout_seed}"
      tail += "" if self.shift is None else f":shift{self.shift:g}"
      return f"floor:{self.rooms}{tail}"
    if self.kind == "synthetic":
      tail = "" if self.domain == "test" else f":{self.domain}"
      tail += "" if self.layout_seed is None else f":s{self.layout_seed}"
      tail += "" if self.shift is None else f":shift{self.shift:g}"
      tail += "" if self.change is None else f":{self.change}"
      return f"{self.env}:{self.trajectory}{tail}"
    return f"{self.kind}:{self.path}"

  @property
  def is_embedded(self) -> bool:
    return self.kind == "synthetic"

  @property
  def is_rendered(self) -> bool:
    """Rendered by the embedded renderer (an embedded sequence or a floor), not read."""
    return self.kind in ("synthetic", "floor")

  def resolved(self, *, layout_seed: int = 0, shift: float = 1.0) -> "SequenceSpec":
    """A rendered spec with its layout seed and shift filled in (the spec's own win); a
    folder's spec unchanged."""
    if not self.is_rendered:
      return self
    return self._replace(layout_seed=int(layout_seed if self.layout_seed is None
                                         else self.layout_seed),
                         shift=float(shift if self.shift is None else self.shift))


_EMBEDDED_SYNTAX = (f"an embedded sequence is ENV:TRAJECTORY[:DOMAIN][:sSEED][:shiftX][:CHANGE] "
                    f"with ENV {'|'.join(synthetic.ENVIRONMENTS)}, TRAJECTORY 0|1|2, DOMAIN "
                    "test|train, a layout seed SEED ≥ 0, a shift X in [0, 1] and one CHANGE "
                    f"{'|'.join(changes.CHANGES)} (e.g. office:0, office:0:s1:shift0.5, "
                    "office:0:moved)")


_FLOOR_SYNTAX = (f"a floor is floor:N[:DOMAIN][:sSEED][:shiftX] with N rooms in "
                 f"1..{floor.MAX_ROOMS}, DOMAIN test|train, a layout seed SEED ≥ 0 and a shift X "
                 "in [0, 1] (e.g. floor:12, floor:12:s3)")


def _floor(rest: str, spec: str) -> SequenceSpec:
  parts = rest.split(":")
  if not parts[0].isdigit() or not 1 <= int(parts[0]) <= floor.MAX_ROOMS:
    raise ValueError(f"{_FLOOR_SYNTAX}; got {spec!r}")
  domain, seed, shift = None, None, None
  for part in parts[1:]:
    if part in DOMAINS and domain is None:
      domain = part
    elif part[:1] == "s" and part[1:].isdigit() and seed is None:
      seed = int(part[1:])
    elif part.startswith("shift") and shift is None:
      try:
        shift = float(part[len("shift"):])
      except ValueError:
        raise ValueError(f"{_FLOOR_SYNTAX}; got {spec!r}") from None
      if not 0.0 <= shift <= 1.0:
        raise ValueError(f"{_FLOOR_SYNTAX}; got {spec!r}")
    else:
      raise ValueError(f"{_FLOOR_SYNTAX}; got {spec!r}")
  return SequenceSpec("floor", domain=domain or "test", layout_seed=seed, shift=shift,
                      rooms=int(parts[0]))


def _embedded(env: str, trajectory: str, tail, spec: str) -> SequenceSpec:
  domain, seed, shift, change = None, None, None, None
  for part in tail:
    if part in DOMAINS and domain is None:
      domain = part
    elif part in changes.CHANGES:
      if change is not None:
        raise ValueError(f"an embedded sequence names one change at most "
                         f"({'|'.join(changes.CHANGES)}); got {change} and {part} in {spec!r}")
      change = part
    elif part[:1] == "s" and part[1:].isdigit() and seed is None:
      seed = int(part[1:])
    elif part.startswith("shift") and shift is None:
      try:
        shift = float(part[len("shift"):])
      except ValueError:
        raise ValueError(f"{_EMBEDDED_SYNTAX}; got {spec!r}") from None
      if not 0.0 <= shift <= 1.0:
        raise ValueError(f"{_EMBEDDED_SYNTAX}; got {spec!r}")
    else:
      raise ValueError(f"{_EMBEDDED_SYNTAX}; got {spec!r}")
  if (env not in synthetic.ENVIRONMENTS or trajectory not in
      tuple(str(t) for t in range(synthetic.NUM_TRAJECTORIES))):
    raise ValueError(f"{_EMBEDDED_SYNTAX}; got {spec!r}")
  return SequenceSpec("synthetic", env=env, trajectory=int(trajectory), domain=domain or "test",
                      layout_seed=seed, shift=shift, change=change)


def parse_spec(spec: str) -> SequenceSpec:
  """Parses a sequence spec (see the module docstring); raises ValueError naming the syntax."""
  if not isinstance(spec, str) or not spec:
    raise ValueError(f"a sequence spec is a non-empty string such as office:0; got {spec!r}")
  head, sep, rest = spec.partition(":")
  if head in ("scannet", "tum", "saved"):
    if not rest:
      raise ValueError(f"{head}: needs a folder, e.g. {head}:PATH; got {spec!r}")
    return SequenceSpec(head, path=rest)
  if head == "floor":
    return _floor(rest, spec)
  if head == "synthetic":            # the older spelling synthetic:ENV/TRAJECTORY[/DOMAIN]
    parts = rest.split("/")
    if len(parts) not in (2, 3):
      raise ValueError(f"synthetic data is synthetic:ENV/TRAJECTORY[/DOMAIN] (or ENV:TRAJECTORY)"
                       f"; got {spec!r}")
    return _embedded(parts[0], parts[1], parts[2:], spec)
  parts = spec.split(":")
  if sep and 2 <= len(parts) <= 6 and parts[0] in synthetic.ENVIRONMENTS:
    return _embedded(parts[0], parts[1], parts[2:], spec)
  raise ValueError(f"a sequence is ENV:TRAJECTORY[:DOMAIN] (e.g. office:0), floor:N (e.g. "
                   f"floor:12), scannet:PATH, tum:PATH or saved:PATH; got {spec!r}")


def load_spec(spec, *, num_frames: Optional[int] = None, height: int = 120, width: int = 160,
              layout_seed: int = 0, shift: float = 1.0, stride: int = 1,
              skip_bad: bool = True, label_space: Optional[str] = None,
              label_tsv: Optional[str] = None,
              **render) -> RGBDSequence:
  """Loads the sequence a spec names.

  Args:
    spec: a spec string or a `SequenceSpec`.
    num_frames: frames of an embedded sequence (default 60); the most frames read from a folder
      or walked through a floor, from the start (default all: a floor's whole walk, one frame
      every `floor.STEP` · stride metres).
    height: image rows of an embedded sequence (folders keep their size).
    width: image columns of an embedded sequence.
    layout_seed: layout seed of the embedded world, unless the spec names one.
    shift: test-domain shift in [0, 1] of an embedded sequence, unless the spec names one.
    stride: keep every stride-th frame of a folder or of a floor's walk.
    skip_bad: skip (and count, with one warning) unreadable frames of a folder.
    label_space: the classes a ScanNet folder's NYU40 GT is read into
      (`classes.LABEL_SPACES`; default "scannet12"); other kinds carry their own classes.
    label_tsv: ScanNet's `scannetv2-labels.combined.tsv`, when the folder's `label-filt/` holds
      raw ScanNet ids (as ScanNet's own 2D label exports do) rather than NYU40 ids.
    **render: passed to `make_sequence` (`realism`, `sensing`), to
      `changes.make_changing_sequence` for a spec with a change, or to
      `floor.make_floor_sequence` for a floor.

  Returns:
    The `RGBDSequence`.

  Raises:
    ValueError: a bad spec, or a folder with no readable frame.
    FileNotFoundError: a folder that does not exist.
  """
  spec = parse_spec(spec) if isinstance(spec, str) else spec
  if spec.kind == "synthetic":
    spec = spec.resolved(layout_seed=layout_seed, shift=shift)
    common = dict(domain=spec.domain, num_frames=60 if num_frames is None else num_frames,
                height=height, width=width, seed=spec.layout_seed, shift=spec.shift)
    if spec.change is not None:
      return changes.make_changing_sequence(spec.env, spec.trajectory, change=spec.change,
                                            **common, **render)
    return synthetic.make_sequence(spec.env, spec.trajectory, **common, **render)
  if spec.kind == "floor":
    spec = spec.resolved(layout_seed=layout_seed, shift=shift)
    return floor.make_floor_sequence(spec.rooms, seed=spec.layout_seed, domain=spec.domain,
                                     shift=spec.shift, num_frames=num_frames, stride=stride,
                                     height=height, width=width, **render)
  if not os.path.isdir(spec.path):
    raise FileNotFoundError(f"{spec.kind}: no such folder {spec.path!r}")
  if spec.kind == "saved":
    seq = RGBDSequence.load(spec.path)
    keep = list(range(0, len(seq), max(int(stride), 1)))[:num_frames]
    ids = list(seq.info.get("frame_ids", range(len(seq))))
    picked = seq if len(keep) == len(seq) else seq.subset(keep)
    return dataclasses.replace(picked, info=dict(picked.info, frame_ids=[ids[i] for i in keep]))
  if spec.kind == "scannet":
    seq = scannet.load_scannet(spec.path, stride=stride, max_frames=num_frames,
                               skip_bad=skip_bad, label_space=label_space or "scannet12",
                               label_tsv=label_tsv)
  else:
    seq = tum.load_tum(spec.path, stride=stride, max_frames=num_frames, skip_bad=skip_bad)
  if len(seq) == 0:
    raise ValueError(f"{spec}: no readable frames")
  return seq


def unit_name(sequence_name: str, layout_seed: int) -> str:
  """The name of a sequence rendered for one layout seed, e.g. `office_0_test_s1`."""
  return f"{sequence_name}_s{int(layout_seed)}"
