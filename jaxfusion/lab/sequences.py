"""The sequences a research command runs on, each with its predictions and its ground truth.

Every command that runs on a set of sequences (`study`, `mesh-study`, `sweep`, `tune-beta`,
`learn-rule`) names them with `--data` (`jaxfusion.datasets.sets`), or by layout seeds of the
embedded world. This module turns one spec into what the commands fuse (`load`):

* the sequence (`datasets.load_spec`: a frame stride and limit, the GT read into the declared
  label space);
* its per-pixel predictions `det`, `mean`, `var` (`(T, H, W, K) float32`): precomputed files
  from `--predictions ROOT/<sequence name>/`, or the front end (the shipped MC-dropout
  network, cached; for an embedded sequence keyed by its layout seed and shift, as the study
  always has), then the `--class-map`;
* its GT voxel labels (`datasets.gt_voxel_labels`).

Precomputed files are matched to frames by number when their names are numbers (`12.npz` or
`000012.npz` is the sequence's frame 12: ScanNet's frame id, or the frame's index in a saved or
embedded sequence); otherwise the i-th file is the i-th frame and the counts must agree. A
frame with no prediction file is an error, or with `missing="skip"` is dropped from the
sequence and counted. A file may hold `det` (a dropout-off pass, which the baseline rules then
read) beside `mean`/`var` or `samples`; without it the baselines read `mean`.

Shape legend: T frames, H×W pixels, K classes.
"""

import dataclasses
import os
from typing import NamedTuple, Optional

import numpy as np
from tqdm.auto import tqdm

from jaxfusion import datasets
from jaxfusion import sources
from jaxfusion.datasets import sets
from jaxfusion.lab import frontend

MISSING = ("error", "skip")


@dataclasses.dataclass(frozen=True)
class DataOptions:
  """How a command reads each sequence of its data.

  Attributes:
    num_frames: frames of an embedded sequence (None: 60).
    max_frames: the most frames read from a folder, after the stride (None: all).
    height: image rows of an embedded sequence.
    width: image columns of an embedded sequence.
    stride: keep every stride-th frame of a folder.
    layout_seed: layout seed of an embedded spec that names none.
    shift: domain shift of an embedded spec that names none.
    predictions: ROOT of precomputed predictions (one folder per sequence), or None for the
      front end.
    missing: a frame without a prediction file: "error" or "skip" (dropped and counted).
    label_space: the classes a ScanNet folder's GT is read into (None: "scannet12").
    label_tsv: ScanNet's label table, when `label-filt/` holds raw ScanNet ids.
    class_map: a `ClassMap` applied to the predictions, or None.
    voxel_size: voxel edge of the GT voxels, metres.
    num_samples: MC-dropout samples M of the front end.
    mc_seed: seed of the MC-dropout keys.
    cache_dir: the front end's cache folder.
  """
  num_frames: Optional[int] = None
  max_frames: Optional[int] = None
  height: int = 120
  width: int = 160
  stride: int = 1
  layout_seed: int = 0
  shift: float = 1.0
  predictions: Optional[str] = None
  missing: str = "error"
  label_space: Optional[str] = None
  label_tsv: Optional[str] = None
  class_map: object = None
  voxel_size: float = 0.1
  num_samples: int = 16
  mc_seed: int = 0
  cache_dir: Optional[str] = None

  def validate(self) -> "DataOptions":
    if self.missing not in MISSING:
      raise ValueError(f"missing predictions must be one of {MISSING}; got {self.missing!r}")
    if int(self.stride) < 1:
      raise ValueError(f"--stride must be at least 1; got {self.stride}")
    for value in (self.num_frames, self.max_frames):
      if value is not None and int(value) < 1:
        raise ValueError(f"--frames must be at least 1; got {value}")
    if self.label_space is not None:
      datasets.classes.label_space(self.label_space)
    return self


class Loaded(NamedTuple):
  """One sequence ready to fuse and score.

  Attributes:
    spec: its spec, with an embedded one's layout seed and shift filled in.
    name: its name in reports (`sets.sequence_name`).
    sequence: the `RGBDSequence` (frames without predictions dropped).
    predictions: `det`, `mean`, `var` (var None when the files hold none), `(T, H, W, K)`.
    gt: GT voxel labels `coords (G, 3) int32`, `labels (G,) int32`, `hits (G,) int32`.
    class_names: the map's classes (the GT's label space).
    source: where the predictions came from, in words.
    skipped: frames dropped for want of a prediction.
  """
  spec: object
  name: str
  sequence: object
  predictions: dict
  gt: dict
  class_names: tuple
  source: str
  skipped: int = 0


def _frame_ids(sequence) -> list:
  ids = sequence.info.get("frame_ids")
  return list(range(len(sequence))) if ids is None else [int(i) for i in ids]


def _numbered(folder: str) -> tuple:
  """`(files, {frame id: path} or None)` of a folder of per-frame `.npz` files: the map when
  every file is named by frame number (`12.npz`, `000012.npz`)."""
  source = sources.precomputed_source(folder)
  stems = [os.path.splitext(os.path.basename(str(f)))[0] for f in source.files]
  if not all(s.isdigit() for s in stems):
    return source.files, None
  return source.files, {int(s): str(f) for s, f in zip(stems, source.files)}


def _covered(ids, by_id: dict, folder: str, missing: str) -> list:
  """Indices of the frame ids `ids` that have a file in `by_id`; a frame without one is an
  error unless `missing == "skip"`."""
  keep = [i for i, fid in enumerate(ids) if int(fid) in by_id]
  if len(keep) < len(ids) and missing == "error":
    absent = [fid for fid in ids if int(fid) not in by_id]
    raise ValueError(f"--predictions {folder} has no file for {len(absent)} of the "
                     f"{len(ids)} frames read (first: frame {absent[0]}); pass "
                     "--missing-predictions skip to drop such frames")
  return keep


def _prediction_files(folder: str, sequence, missing: str) -> tuple:
  """`(files per kept frame, kept frame indices)` of a folder of per-frame `.npz` files."""
  files, by_id = _numbered(folder)
  if by_id is not None:
    ids = _frame_ids(sequence)
    keep = _covered(ids, by_id, folder, missing)
    return [by_id[ids[i]] for i in keep], keep
  if len(files) != len(sequence):
    raise ValueError(f"--predictions {folder} has {len(files)} files but the sequence "
                     f"has {len(sequence)} frames (name the files by frame number to match "
                     "them to frames)")
  return [str(f) for f in files], list(range(len(sequence)))


def _read_frame(path: str, class_map) -> tuple:
  """`(det or None, mean, var or None)` of one precomputed file (read once), remapped by
  `class_map` (samples before their moments, where the file holds samples)."""
  frame = sources.PrecomputedSource((path,)).read(0)
  det = frame.extra.get("det")
  if det is not None:
    det = np.asarray(det, np.float32)
    size = frame.probs.shape[:2] if frame.samples is None else frame.samples.shape[1:3]
    if det.shape[:2] != tuple(size):
      raise ValueError(f"{path}: 'det' {det.shape} must be (H, W, K) as 'mean'")
  if frame.samples is None:
    return _remapped(class_map, det, frame.probs, frame.var, path)
  if class_map is None:
    mean, var = sources.mc_moments(frame.samples)
  else:
    _check_k(class_map, frame.samples.shape[-1], path)
    mean, var = sources.mc_moments(class_map.remap_samples(frame.samples))
  return _remapped(class_map, det, None, None, path)[0], np.asarray(mean), np.asarray(var)


def _remapped(class_map, det, mean, var, where: str) -> tuple:
  """`(det, mean, var)` as float32 arrays (None stays None), remapped by `class_map`."""
  as32 = lambda x: None if x is None else np.asarray(x, np.float32)
  if class_map is None:
    return as32(det), as32(mean), as32(var)
  for x in (det, mean):
    if x is not None:
      _check_k(class_map, np.shape(x)[-1], where)
  if mean is not None:
    mean, var = class_map.remap(mean, var)
  if det is not None:
    det = class_map.remap(det)[0]
  return as32(det), as32(mean), as32(var)


def _check_classes(name: str, class_names, k: int) -> None:
  """Refuses predictions of K classes for GT of another label space."""
  if class_names and len(class_names) != k:
    raise ValueError(f"{name}: the predictions have {k} classes but the GT's label space has "
                     f"{len(class_names)} ({', '.join(class_names)}); give --class-map, or "
                     "--label-space for the predictions' classes")


def _check_k(class_map, k: int, path: str) -> None:
  if k != class_map.num_source_classes:
    raise ValueError(f"--class-map maps {class_map.num_source_classes} source classes but "
                     f"{path} has {k}")


def precomputed(folder: str, sequence, *, class_map=None, missing: str = "error") -> tuple:
  """A sequence's precomputed predictions and the frames they cover.

  Returns:
    `(predictions, keep)`: `det`, `mean`, `var` stacked `(T', H, W, K)` over the kept frames
    `keep` (indices into the sequence).
  """
  files, keep = _prediction_files(folder, sequence, missing)
  if not files:
    raise ValueError(f"--predictions {folder} covers none of the sequence's frames")
  h, w = sequence.image_size
  frames = []
  for path in tqdm(files, desc="predictions", leave=False):
    frames.append(_read_frame(path, class_map))
    mean = frames[-1][1]
    if mean.shape[:2] != (h, w):
      raise ValueError(f"{path}: the prediction is {mean.shape[0]}x{mean.shape[1]} pixels but "
                       f"the sequence's depth is {h}x{w}")
  if len({m.shape[-1] for _, m, _ in frames}) != 1:
    raise ValueError(f"--predictions {folder}: the files disagree on the number of classes")
  return _stack(frames), keep


def _front_end_predictions(front_end, spec, sequence, options: DataOptions) -> dict:
  seed = spec.layout_seed if spec.is_embedded else 0
  shift = spec.shift if spec.is_embedded else 0.0
  preds = frontend.cached_predictions(front_end, sequence, layout_seed=seed, shift=shift,
                                      num_samples=options.num_samples, mc_seed=options.mc_seed,
                                      cache_dir=options.cache_dir or "outputs/cache")
  det, mean, var = _remapped(options.class_map, preds["det"], preds["mean"], preds["var"],
                             f"the front end {front_end.model_id}")
  return {"det": det, "mean": mean, "var": var}


# `load(..., front_end=SIMULATED)`: the simulated noisy network drawn from the GT labels.
SIMULATED = "simulated"


def _simulated(spec, name: str, sequence, options: DataOptions) -> dict:
  """The simulated network's moments (`frontend.simulated_predictions`), drawn from the GT
  labels; an embedded sequence keeps its own stream (environment, trajectory), a folder's is
  keyed by its name."""
  if sequence.labels is None:
    raise ValueError(f"{spec}: the simulated front end draws from GT labels, and it has none")
  env, trajectory = (spec.env, spec.trajectory) if spec.is_embedded else (name, 0)
  preds = frontend.simulated_predictions(sequence.labels, env=env, trajectory=trajectory,
                                         num_classes=len(sequence.class_names),
                                         num_samples=options.num_samples,
                                         mc_seed=options.mc_seed)
  return {"det": preds["mean"], "mean": preds["mean"], "var": preds["var"]}


def load(spec, options: DataOptions, *, front_end=None, gt: bool = True) -> Loaded:
  """Loads one sequence with its predictions and GT voxel labels.

  Args:
    spec: a spec string or `SequenceSpec`.
    options: how to read it.
    front_end: a front end (`frontend.FrontEnd` or the same protocol), or `SIMULATED`, for
      sequences without `options.predictions`.
    gt: compute the GT voxel labels (the sequence must have GT labels).

  Returns:
    A `Loaded`.

  Raises:
    ValueError: no GT labels, predictions of another K than the GT's label space, a front end
      missing where there are no predictions, …; one line each.
  """
  spec = datasets.parse_spec(spec) if isinstance(spec, str) else spec
  spec = spec.resolved(layout_seed=options.layout_seed, shift=options.shift)
  name = sets.sequence_name(spec)
  frames = options.num_frames if spec.is_embedded else options.max_frames
  sequence = datasets.load_spec(spec, num_frames=frames, height=options.height,
                                width=options.width, stride=options.stride,
                                label_space=options.label_space, label_tsv=options.label_tsv)
  skipped = 0
  if options.predictions is not None:
    folder = sets.predictions_folder(options.predictions, spec)
    preds, keep = precomputed(folder, sequence, class_map=options.class_map,
                              missing=options.missing)
    if len(keep) < len(sequence):
      skipped = len(sequence) - len(keep)
      tqdm.write(f"{name}: {skipped} of {len(sequence)} frames have no prediction in {folder}; "
                 "skipped")
      # The subset's own info: the entries that name frames (`gt_frames`, `true_poses`, …)
      # follow the frames kept.
      ids = _frame_ids(sequence)
      sequence = sequence.subset(keep)
      sequence = dataclasses.replace(sequence, info=dict(
          sequence.info, frame_ids=[ids[i] for i in keep], skipped_without_prediction=skipped))
    source = f"precomputed predictions in {folder}"
  elif front_end == SIMULATED:
    preds = _simulated(spec, name, sequence, options)
    source = f"simulated network (M={options.num_samples})"
  else:
    if front_end is None:
      raise ValueError(f"{spec}: no --predictions and no front end to predict with")
    preds = _front_end_predictions(front_end, spec, sequence, options)
    source = f"network {front_end.model_id} (MC dropout, M={options.num_samples})"
  k = int(preds["mean"].shape[-1])
  class_names = tuple(sequence.class_names)
  _check_classes(name, class_names, k)
  voxels = None
  if gt:
    if sequence.labels is None:
      raise ValueError(f"{spec} has no GT labels to score against (ScanNet: label-filt/; a "
                       "saved sequence: labels)")
    voxels = datasets.gt_voxel_labels(sequence, voxel_size=options.voxel_size)
  return Loaded(spec=spec, name=name, sequence=sequence, predictions=preds, gt=voxels,
                class_names=class_names or tuple(str(i) for i in range(k)), source=source,
                skipped=skipped)


# --- streaming: a long sequence chunk by chunk -------------------------------------------------
# Bytes of predictions (det, mean, var) one chunk may hold when the chunk size is automatic.
CHUNK_BYTES = 256 * 2**20


def chunk_frames(image_size, num_classes: int, budget: int = CHUNK_BYTES) -> int:
  """Frames per chunk whose predictions (`det`, `mean`, `var`, float32) fit `budget` bytes
  (1 to 16)."""
  per_frame = 3 * 4 * int(image_size[0]) * int(image_size[1]) * int(num_classes)
  return int(max(1, min(16, budget // max(per_frame, 1))))


class Streamed:
  """One sequence of `--data` read from disk a chunk at a time, with its predictions and GT.

  `gt()` makes the GT voxel labels in a first pass over the frames (`ground_truth.
  gt_from_frames`, into a map that grows); `chunks()` yields `(frames, predictions)` pairs of
  at most `chunk` frames; frames without a prediction file are dropped in both passes (or
  are an error: `options.missing`). Neither pass holds more than one chunk. Predictions come
  from precomputed files, or from a network front end frame by frame (MC keys
  `fold_in(PRNGKey(mc_seed), t)` of the frame's index t, as `frontend.FrontEnd.predict`); an
  embedded sequence, which is small, is loaded whole (`load`).

  Attributes:
    spec, name, class_names, camera, image_size: the sequence's.
    skipped: frames dropped for want of a prediction (known after a pass).
    frames: frames yielded by the last pass.
  """

  def __init__(self, spec, options: DataOptions, *, front_end=None, chunk=None):
    from jaxfusion.datasets import stream  # pylint: disable=import-outside-toplevel
    spec = datasets.parse_spec(spec) if isinstance(spec, str) else spec
    self.spec = spec.resolved(layout_seed=options.layout_seed, shift=options.shift)
    self.name = sets.sequence_name(self.spec)
    self.options, self.front_end, self._chunk = options, front_end, chunk
    self._loaded = None
    if self.spec.is_embedded:
      self._loaded = load(self.spec, options, front_end=front_end, gt=False)
      first = self._loaded.sequence
    else:
      self.stream = stream.open_stream(self.spec, num_frames=options.max_frames,
                                       stride=options.stride, label_space=options.label_space,
                                       label_tsv=options.label_tsv)
      first = self.stream.first()
    self.class_names = tuple(first.class_names)
    self.camera, self.image_size = first.camera, first.image_size
    self.skipped, self.frames = 0, 0
    self._folder = None
    if self._loaded is None:
      if options.predictions is not None:
        self._folder = sets.predictions_folder(options.predictions, self.spec)
        files, self._files = _numbered(self._folder)
        if self._files is None:
          bad = next(f for f in files if not os.path.splitext(os.path.basename(str(f)))[0]
                     .isdigit())
          raise ValueError(f"--predictions {self._folder}: {os.path.basename(str(bad))} is not "
                           "named by frame number (e.g. 000012.npz for frame 12), which a "
                           "streamed sequence needs")
        self.source = f"precomputed predictions in {self._folder}"
      elif front_end is None or front_end == SIMULATED:
        raise ValueError(f"{self.spec}: streaming needs --predictions or a network front end")
      else:
        self.source = f"network {front_end.model_id} (MC dropout, M={options.num_samples})"
    else:
      self.source = self._loaded.source

  def _raw_chunks(self, size: int):
    if self._loaded is not None:
      for lo in range(0, len(self._loaded.sequence), size):
        yield (*self._loaded_chunk(lo, size), None)
      return
    offset = 0
    for chunk in self.stream.chunks(size):
      yield chunk, None, list(range(offset, offset + len(chunk)))
      offset += len(chunk)

  def _loaded_chunk(self, lo: int, size: int) -> tuple:
    """Frames `lo … lo + size` of a sequence loaded whole, with their predictions."""
    seq = self._loaded.sequence
    idx = list(range(lo, min(len(seq), lo + size)))
    return seq.subset(idx), {k: None if v is None else v[idx]
                             for k, v in self._loaded.predictions.items()}

  def _keep(self, chunk) -> list:
    """Indices of a chunk's frames that have a prediction file (the rest: error or skip)."""
    if self._folder is None:
      return list(range(len(chunk)))
    return _covered(chunk.info.get("frame_ids") or [], self._files, self._folder,
                    self.options.missing)

  def _size(self) -> int:
    if self._chunk is not None:
      return int(self._chunk)
    k = len(self.class_names) or 1
    return chunk_frames(self.image_size, k)

  def gt(self) -> dict:
    """GT voxel labels of the frames that have predictions (a pass over the frames); of a
    changing world's final-scene frames, at its true poses (`ground_truth.gt_part`), as
    `datasets.gt_voxel_labels` makes them."""
    from jaxfusion.datasets import ground_truth  # pylint: disable=import-outside-toplevel
    if not self.class_names:
      raise ValueError(f"{self.spec} has no GT labels to score against")

    def labelled():
      for chunk, _, _ in self._raw_chunks(self._size()):
        if chunk.labels is None:
          raise ValueError(f"{self.spec} has no GT labels to score against (ScanNet: "
                           "label-filt/; a saved sequence: labels)")
        keep = self._keep(chunk)
        if keep:
          yield ground_truth.gt_part(chunk if len(keep) == len(chunk) else chunk.subset(keep))

    return ground_truth.gt_from_frames(labelled(), camera=self.camera,
                                       num_classes=len(self.class_names),
                                       voxel_size=self.options.voxel_size)

  def chunks(self):
    """`(frames, predictions)` chunk by chunk, with a progress bar."""
    self.skipped, self.frames = 0, 0
    bar = tqdm(total=self._length(), desc=self.name, leave=False)
    for chunk, preds, positions in self._raw_chunks(self._size()):
      bar.update(len(chunk))
      prepared = self._prepare(chunk, preds, positions)
      if prepared is not None:
        self.frames += len(prepared[0])
        yield prepared
    bar.close()

  def _length(self) -> int:
    return len(self.stream) if self._loaded is None else len(self._loaded.sequence)

  @property
  def num_chunks(self) -> int:
    """How many chunks `chunk(k)` reads."""
    return -(-self._length() // self._size())

  @property
  def chunk_size(self) -> int:
    """Frames per chunk (the last may hold fewer)."""
    return self._size()

  def chunk(self, k: int):
    """Chunk k alone, `(frames, predictions)`, or None when none of its frames is readable or
    has a prediction (random access, for the backward passes of `tune_chunks`)."""
    size = self._size()
    if self._loaded is not None:
      return self._loaded_chunk(k * size, size)
    chunk = self.stream._read(k * size, size)   # pylint: disable=protected-access
    if chunk is None or not len(chunk):
      return None
    return self._prepare(chunk, None, list(range(k * size, k * size + len(chunk))))

  def _prepare(self, chunk, preds, positions):
    """A raw chunk with its predictions (read or predicted), frames without one dropped."""
    import jax  # pylint: disable=import-outside-toplevel
    if preds is None:
      keep = self._keep(chunk)
      self.skipped += len(chunk) - len(keep)
      if not keep:
        return None
      chunk = chunk if len(keep) == len(chunk) else chunk.subset(keep)
      if self._folder is not None:
        preds = _stack([_read_frame(self._files[int(chunk.info["frame_ids"][i])],
                                    self.options.class_map) for i in range(len(chunk))])
      else:
        preds = self._predict(chunk, [positions[i] for i in keep],
                              jax.random.PRNGKey(self.options.mc_seed))
    self._check(preds)
    return chunk, preds

  def _predict(self, chunk, positions, key) -> dict:
    import jax  # pylint: disable=import-outside-toplevel
    out = []
    for t, position in enumerate(positions):
      det = self.front_end.deterministic(chunk.rgb[t])
      mean, var = self.front_end.mc(chunk.rgb[t], num_samples=self.options.num_samples,
                                    key=jax.random.fold_in(key, position))
      out.append(_remapped(self.options.class_map, det, mean, var,
                           f"the front end {self.front_end.model_id}"))
    return _stack(out)

  def _check(self, preds: dict) -> None:
    _check_classes(self.name, self.class_names, int(preds["mean"].shape[-1]))
    if tuple(preds["mean"].shape[1:3]) != tuple(self.image_size):
      raise ValueError(f"{self.name}: the predictions are {preds['mean'].shape[1]}x"
                       f"{preds['mean'].shape[2]} pixels but the depth is "
                       f"{self.image_size[0]}x{self.image_size[1]}")


def _stack(frames: list) -> dict:
  """`{det, mean, var}` stacked from per-frame `(det or None, mean, var or None)`."""
  mean = np.stack([m for _, m, _ in frames])
  var = None if any(v is None for _, _, v in frames) else np.stack([v for _, _, v in frames])
  det = mean if any(d is None for d, _, _ in frames) else np.stack([d for d, _, _ in frames])
  return {"det": det, "mean": mean, "var": var}
