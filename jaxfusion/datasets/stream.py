"""A sequence read from disk chunk by chunk: long sequences in bounded memory.

`open_stream(spec, ...)` indexes a sequence without reading its images (ScanNet: the file
names; TUM: the association of its lists; a saved sequence: its `meta.json`) and
`stream.chunks(size)` yields it as `RGBDSequence`s of at most `size` frames, each with
`info["frame_ids"]`, so that no more than one chunk is ever held. An embedded sequence is
rendered whole (it is small) and sliced.

The frames a stream yields are the frames `load_spec` reads with the same arguments, in the
same order (a floor's walk is rendered chunk by chunk, `floor.FloorWalk`; a frame whose pose turns out invalid on reading is skipped and counted the same
way), so a result computed chunk by chunk is the result of the whole sequence.
"""

import json
import os
from typing import Iterator, Optional

from jaxfusion.datasets import scannet
from jaxfusion.datasets import specs as specs_lib
from jaxfusion.datasets import tum
from jaxfusion.datasets.sequence import RGBDSequence


class SequenceStream:
  """A sequence's frames, read a chunk at a time.

  Attributes:
    spec: the `SequenceSpec` (an embedded one with its layout seed and shift filled in).
    frame_ids: the ids of the frames it will read (ScanNet's frame numbers; a saved
      sequence's frame indices; a TUM sequence's positions in its association).
  """

  def __init__(self, spec, *, num_frames: Optional[int] = None, height: int = 120,
               width: int = 160, layout_seed: int = 0, shift: float = 1.0, stride: int = 1,
               skip_bad: bool = True, label_space: Optional[str] = None,
               label_tsv: Optional[str] = None, **render):
    spec = specs_lib.parse_spec(spec) if isinstance(spec, str) else spec
    self.spec = spec.resolved(layout_seed=layout_seed, shift=shift)
    self._stride = max(int(stride), 1)
    self._skip_bad = skip_bad
    self._label_space = label_space
    self._label_tsv = label_tsv
    self._whole = None
    self._walk = None
    if int(stride) < 1:
      raise ValueError(f"stride must be ≥ 1; got {stride}")
    if self.spec.kind == "floor":
      from jaxfusion.datasets import floor  # pylint: disable=import-outside-toplevel
      self._walk = floor.FloorWalk(
          floor.make_floor(self.spec.rooms, seed=self.spec.layout_seed, domain=self.spec.domain,
                           shift=self.spec.shift),
          num_frames=num_frames, stride=self._stride, height=height, width=width, **render)
      self.frame_ids = list(range(len(self._walk)))
      return
    if self.spec.is_embedded:
      self._whole = specs_lib.load_spec(self.spec, num_frames=num_frames, height=height,
                                        width=width, **render)
      self.frame_ids = list(range(len(self._whole)))
      return
    if not os.path.isdir(self.spec.path):
      raise FileNotFoundError(f"{self.spec.kind}: no such folder {self.spec.path!r}")
    if self.spec.kind == "scannet":
      self.frame_ids = scannet.frame_ids(self.spec.path, stride=self._stride,
                                         max_frames=num_frames, skip_bad=skip_bad)
    elif self.spec.kind == "tum":
      matched, _ = tum.associate(self.spec.path)
      self.frame_ids = list(range(len(matched)))[::self._stride][:num_frames]
    else:
      meta_path = os.path.join(self.spec.path, "meta.json")
      if not os.path.isfile(meta_path):
        raise FileNotFoundError(f"not a saved sequence: {meta_path} is missing")
      with open(meta_path, encoding="utf-8") as f:
        count = int(json.load(f)["num_frames"])
      self.frame_ids = list(range(0, count, self._stride))[:num_frames]
    if not self.frame_ids:
      raise ValueError(f"{self.spec}: no readable frames")

  def __len__(self) -> int:
    return len(self.frame_ids)

  def _read(self, position: int, size: int) -> Optional[RGBDSequence]:
    """Frames `frame_ids[position:position + size]` (None when all of them are unreadable)."""
    ids = self.frame_ids[position:position + size]
    if self._walk is not None:
      return self._walk.sequence(position, position + len(ids))
    if self._whole is not None:
      chunk = self._whole.subset(range(position, position + len(ids)))
      return _with_ids(chunk, ids)
    kind, path = self.spec.kind, self.spec.path
    try:
      if kind == "scannet":
        return scannet.load_scannet(path, frame_ids=ids, skip_bad=self._skip_bad,
                                    label_space=self._label_space or "scannet12",
                                    label_tsv=self._label_tsv)
      if kind == "tum":
        return tum.load_tum(path, stride=self._stride, first=position, max_frames=len(ids),
                            skip_bad=self._skip_bad)
    except ValueError as e:
      if "no valid frames" in str(e):
        return None
      raise
    return _with_ids(RGBDSequence.load(path, frames=ids), ids)

  def chunks(self, size: int) -> Iterator[RGBDSequence]:
    """The sequence as consecutive chunks of at most `size` frames (`info["frame_ids"]`)."""
    if int(size) < 1:
      raise ValueError(f"a chunk holds at least one frame; got {size}")
    for position in range(0, len(self.frame_ids), int(size)):
      chunk = self._read(position, int(size))
      if chunk is not None and len(chunk):
        yield chunk

  def first(self) -> RGBDSequence:
    """The first readable frame, as a one-frame sequence (its name, classes, camera, size)."""
    for chunk in self.chunks(1):
      return chunk
    raise ValueError(f"{self.spec}: no readable frames")


def _with_ids(chunk: RGBDSequence, ids) -> RGBDSequence:
  import dataclasses  # pylint: disable=import-outside-toplevel
  return dataclasses.replace(chunk, info=dict(chunk.info, frame_ids=list(ids)))


def open_stream(spec, **kwargs) -> SequenceStream:
  """A `SequenceStream` of a spec (`load_spec`'s arguments: `num_frames`, `height`, `width`,
  `layout_seed`, `shift`, `stride`, `skip_bad`, `label_space`, `label_tsv`, rendering
  options)."""
  return SequenceStream(spec, **kwargs)
