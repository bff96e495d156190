"""Front ends: where the commands' per-pixel class probabilities come from, and their cache.

A front end is any object with
  - `model_id: str`, which names its outputs in the cache, and
  - `predict(rgb, *, num_samples, key) -> (det, mean, var)`: for `(T, H, W, 3) uint8` images,
    one dropout-off pass and the MC-dropout moments (`mc_moments` of M samples), each
    `(T, H, W, K) float32`.

`FrontEnd` is the shipped MC-dropout network (or any checkpoint). Two other sources give the
same arrays without a network: `simulated_predictions` (a simulated noisy Bayesian net drawn
from the GT labels, `simulation.simulate_predictions`) and `precomputed_predictions` (one `.npz` per
frame, `sources.precomputed_source`). `sequence_predictions` picks one of the three for a
command.

The cache (`cached_predictions`) stores a network's outputs once per rendered sequence: one
`.npz` per sequence and model, written to a temporary file and renamed, whose name carries the
model's digest, the layout seed, shift, resolution, frame count, M, the MC seed and a digest of
the rendered images, and whose metadata (that key, and a digest of the arrays) is checked when
it is read (`read_cache_entry`). An entry that is damaged, truncated or of another key is
reported in one line and recomputed.
"""

import hashlib
import json
import os
from typing import Optional

import jax
import numpy as np
from tqdm.auto import tqdm

from jaxfusion import io
from jaxfusion import simulation
from jaxfusion import sources

CACHE_VERSION = 2
# The front ends a command can name with --front-end.
KINDS = ("shipped", "simulated")


def file_digest(path: str) -> str:
  """The first 16 hex digits of a file's SHA-256 (a checkpoint's model id)."""
  h = hashlib.sha256()
  with open(path, "rb") as f:
    for chunk in iter(lambda: f.read(1 << 20), b""):
      h.update(chunk)
  return h.hexdigest()[:16]


class FrontEnd:
  """An MC-dropout segmentation network (default: the shipped weights) as a front end.

  Args:
    checkpoint: path of a `jaxfusion_models` checkpoint (default `PRETRAINED_PATH`).
    class_names: the classes the network must predict, in order (default the embedded world's);
      None accepts any.
  """

  def __init__(self, checkpoint: Optional[str] = None, *, class_names="embedded"):
    import jaxfusion_models as models  # pylint: disable=import-outside-toplevel
    from jaxfusion import datasets  # pylint: disable=import-outside-toplevel
    self._models = models
    path = checkpoint or models.PRETRAINED_PATH
    names = datasets.CLASS_NAMES if class_names == "embedded" else class_names
    self.model = models.load(path, class_names=names)
    self.model_id = file_digest(str(path))

  @property
  def class_names(self) -> tuple:
    return tuple(self.model.class_names)

  def deterministic(self, image: np.ndarray) -> np.ndarray:
    """`(H, W, 3) uint8` → `(H, W, K)` probabilities of one dropout-off pass."""
    return np.asarray(self._models.deterministic_probs(self.model.graphdef, self.model.params,
                                                       image))

  def mc_samples(self, image: np.ndarray, *, num_samples: int, key) -> jax.Array:
    """`(H, W, 3) uint8` → `(M, H, W, K) float32` MC-dropout softmax samples (the ones `mc`
    takes the moments of, for the same key)."""
    return self._models.mc_samples(self.model.graphdef, self.model.params, key, image,
                                   num_samples=num_samples)

  def mc(self, image: np.ndarray, *, num_samples: int, key) -> tuple:
    """`(H, W, 3) uint8` → MC-dropout `(mean, var)`, each `(H, W, K)`, from M samples."""
    samples = self.mc_samples(image, num_samples=num_samples, key=key)
    mean, var = sources.mc_moments(samples)
    return np.asarray(mean), np.asarray(var)

  def predict(self, rgb: np.ndarray, *, num_samples: int, key) -> tuple:
    """`(T, H, W, 3) uint8` → deterministic probs, MC mean, MC var, each `(T, H, W, K)`; frame t
    samples with `fold_in(key, t)`."""
    det, mean, var = [], [], []
    for t in tqdm(range(len(rgb)), desc="front end", leave=False):
      det.append(self.deterministic(rgb[t]))
      m, v = self.mc(rgb[t], num_samples=num_samples, key=jax.random.fold_in(key, t))
      mean.append(m)
      var.append(v)
    return np.stack(det), np.stack(mean), np.stack(var)


def cache_path(cache_dir: str, model_id: str, sequence_id: str) -> str:
  """Where `cached_predictions` keeps one sequence's outputs of one model."""
  return os.path.join(cache_dir, f"{sequence_id}__model-{model_id}.npz")


def cache_sequence_id(sequence, *, layout_seed: int, shift: float, num_samples: int,
                      mc_seed: int) -> str:
  """The cache's name for a rendered sequence: what makes its front-end outputs what they are."""
  height, width = np.shape(sequence.rgb)[1:3]
  rgb_digest = hashlib.sha256(np.ascontiguousarray(sequence.rgb).tobytes()).hexdigest()[:12]
  return (f"{sequence.name}_s{layout_seed}_{height}x{width}_T{len(sequence)}_M{num_samples}"
          f"_seed{mc_seed}_shift{float(shift)}_rgb{rgb_digest}")


def cached_predictions(front_end, sequence, *, layout_seed: int, shift: float,
                       num_samples: int, mc_seed: int, cache_dir: str) -> dict:
  """The front end's outputs for a sequence, computed once and cached (write then rename).

  A cache written for another model, sequence or M is never used: the file name carries the
  model's digest and `cache_sequence_id`, and the metadata inside is checked. An entry that
  cannot be read whole (truncated, damaged, arrays of the wrong shape, a digest mismatch) is
  reported in one line and recomputed.

  Args:
    front_end: a front end (`model_id`, `predict`).
    sequence: the rendered `RGBDSequence` (its `name`, `rgb`).
    layout_seed: the layout seed it was rendered with.
    shift: the domain shift it was rendered with.
    num_samples: M.
    mc_seed: seed of the MC-dropout keys (`PRNGKey(mc_seed)`, folded with the frame index).
    cache_dir: the cache folder.

  Returns:
    dict with `det`, `mean`, `var`, each `(T, H, W, K) float32`.
  """
  seq_id = cache_sequence_id(sequence, layout_seed=layout_seed, shift=shift,
                             num_samples=num_samples, mc_seed=mc_seed)
  path = cache_path(cache_dir, front_end.model_id, seq_id)
  meta = {"version": CACHE_VERSION, "model": front_end.model_id, "sequence": seq_id}
  if os.path.exists(path):
    try:
      return read_cache_entry(path, meta, frames=len(sequence),
                              image_size=np.shape(sequence.rgb)[1:3])
    except StaleCacheError as e:
      tqdm.write(f"cache {path} was made for {e.args[0]}; recomputing")
    except (io.BadFileError, OSError) as e:
      tqdm.write(f"cache {path} is unreadable ({_reason(path, e)}); recomputing")
  det, mean, var = front_end.predict(sequence.rgb, num_samples=num_samples,
                                     key=jax.random.PRNGKey(mc_seed))
  arrays = {"det": np.asarray(det, np.float32), "mean": np.asarray(mean, np.float32),
            "var": np.asarray(var, np.float32)}
  stored = {**meta, "digest": io.array_digest(arrays)}

  def write(tmp):
    with open(tmp, "wb") as f:
      np.savez(f, **arrays, meta=np.frombuffer(json.dumps(stored).encode(), np.uint8))

  io.atomic_write(path, write)
  return arrays


CACHE_FILE = "front-end cache entry"
CACHE_ARRAYS = ("det", "mean", "var")


class StaleCacheError(Exception):
  """A whole cache entry written for another key (its stored key is `args[0]`)."""


def _reason(path: str, error: Exception) -> str:
  """The part of a reader's message after the path (it is printed with the path already)."""
  text = str(error)
  prefix = f"{path} is not a {CACHE_FILE} ("
  return text[len(prefix):-1] if text.startswith(prefix) and text.endswith(")") else text


def read_cache_entry(path: str, meta: dict, *, frames: Optional[int] = None,
                     image_size=None) -> dict:
  """Reads one entry of the front-end cache, refusing anything not whole or not its key's.

  An entry holds `det`, `mean`, `var` (`(T, H, W, K) float32`, one shape) and `meta`: JSON
  with the `version`, `model` and `sequence` of its key and, for entries written since it was
  added, `digest` (`io.array_digest` of the three arrays). Entries without a digest are still
  used: their zip CRCs are checked on reading and their key must match.

  Args:
    path: the entry.
    meta: the key it must carry (`version`, `model`, `sequence`).
    frames: T, when known.
    image_size: `(H, W)`, when known.

  Returns:
    dict with `det`, `mean`, `var`.

  Raises:
    FileNotFoundError: no file.
    io.BadFileError: damaged, not a cache entry, wrong shapes/dtypes or a digest mismatch.
    StaleCacheError: a whole entry of another key.
  """
  data = io.read_npz(path, what=CACHE_FILE, required=(*CACHE_ARRAYS, "meta"))
  stored = io.read_json_array(path, CACHE_FILE, data["meta"])
  digest = stored.pop("digest", None)
  if stored != meta:
    raise StaleCacheError(stored)
  arrays = {k: data[k] for k in CACHE_ARRAYS}
  h, w = (None, None) if image_size is None else (int(image_size[0]), int(image_size[1]))
  shape = (frames, h, w, None)
  for name, value in arrays.items():
    io.check_array(path, CACHE_FILE, name, value, shape, np.float32)
    shape = value.shape
  if digest is not None and digest != io.array_digest(arrays):
    raise io.BadFileError(f"{path} is not a {CACHE_FILE} (its arrays do not match their "
                          "digest)")
  return arrays


def simulated_predictions(labels: np.ndarray, *, env: str, trajectory: int, num_classes: int,
                          num_samples: int, mc_seed: int) -> dict:
  """The simulated noisy Bayesian network's MC moments for a labelled embedded sequence.

  Args:
    labels: `(T, H, W) int` GT labels.
    env: the sequence's environment (with `trajectory`, it picks the sequence's own stream).
    trajectory: its trajectory index.
    num_classes: K.
    num_samples: M.
    mc_seed: seed of the simulated samples.

  Returns:
    dict with `mean` and `var`, each `(T, H, W, K) float32`.
  """
  key = jax.random.fold_in(jax.random.PRNGKey(mc_seed), 97 * trajectory + len(env))
  mean, var = simulation.simulate_predictions(key, labels, num_classes=num_classes,
                                              num_samples=num_samples)
  return {"mean": np.asarray(mean, np.float32), "var": np.asarray(var, np.float32)}


def precomputed_predictions(folder: str, sequence) -> dict:
  """Per-frame predictions read from a folder of `.npz` files (`sources.precomputed_source`).

  Returns:
    dict with `mean` `(T, H, W, K)` and `var` (same shape, or None when the files have none).

  Raises:
    ValueError: the folder holds another number of frames than the sequence.
  """
  src = sources.precomputed_source(folder)
  if len(src) != len(sequence):
    raise ValueError(f"{folder} has {len(src)} prediction files but the sequence has "
                     f"{len(sequence)} frames")
  preds = [src.predict(None, None, index=i) for i in range(len(sequence))]
  var = None if preds[0].var is None else np.stack([np.asarray(p.var) for p in preds])
  return {"mean": np.stack([np.asarray(p.probs) for p in preds]), "var": var}
