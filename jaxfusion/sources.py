"""Sources of per-pixel class probabilities, and their Monte-Carlo moments.

The engine never imports a network. A front end plugs in as a `ProbabilitySource`: anything
with `predict(key, image, *, index=None) -> Prediction(probs, var)`, where `probs` is the
`(H, W, K)` class distribution fed to `Frame.probs` and `var` the per-class epistemic
variance fed to `Frame.var` (None for a deterministic network). Adapters build one from:

* a `segment_fn(params, key, image) -> samples (M, H, W, K)` (`segment_fn_source`), the most
  general form: any JAX network, any sampling scheme;
* an `apply_fn(params, key, image) -> probs (H, W, K)` that is stochastic in `key`
  (`mc_dropout_source`: M dropout keys under one `jax.vmap`), deterministic
  (`deterministic_source`: one pass, no variance), or a list of parameter sets
  (`ensemble_source`: one pass per member, `vmap`ped over the stacked parameters);
* files on disk (`precomputed_source`): one `.npz` per frame holding `mean` (and optionally
  `var`) or `samples` — the way to fuse predictions of a network in another framework
  (PyTorch included) without touching the engine.

Example:
  >>> source = jaxfusion.sources.mc_dropout_source(apply_fn, params, num_samples=32)
  >>> pred = source.predict(jax.random.key(0), rgb)
  >>> frame = jaxfusion.Frame(depth, T_world_cam, pred.probs, pred.var)

Shape legend: M Monte-Carlo samples (or ensemble members), B frames, H×W pixels, K classes.
"""

import dataclasses
import functools
import os
import pathlib
from typing import Any, Callable, NamedTuple, Optional, Protocol, Sequence, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion import io
from jaxfusion.classmap import ClassMap  # noqa: F401  (re-exported: sources.ClassMap)


# Samples summed in one fused pass: `mc_moments` adds up to this many (H, W, K) samples in one
# elementwise loop (each output value reads its M inputs once), then adds the group's sums to the
# running ones. XLA on CPU reduces over a leading axis slowly (a (32, 480, 640, 13) `jnp.sum(x, 0)`
# took 13× NumPy's `x.sum(0)`; a `fori_loop` over M 2.5–4×); this form costs what NumPy's sum does
# (`python -m bench.micro moments`).
_MOMENT_GROUP = 32


def mc_moments(samples: jax.Array) -> tuple[jax.Array, jax.Array]:
  """Mean and per-class epistemic variance of Monte-Carlo class probabilities, in one pass.

  As in docs/equations.md §2.3: `p̄ = mean_s p^(s)` and `var_i = mean_s (p^(s)_i − p̄_i)^2` (the
  diagonal of the paper's Σe, population variance over the M samples). Computed in one read of the
  samples from the sums of `d_s = p^(s) − p^(0)` (shifted by the first sample, so constant samples
  give exactly zero variance and no large sums cancel): `p̄ = p^(0) + Σd/M`, `var = max(Σd²/M −
  (Σd/M)², 0)` — never negative, and within ~1e-7 of a float64 two-pass result for probabilities
  (one-hot samples included).

  The checks run in Python and the arithmetic as one compiled program per shape (`_moments`), so
  a plain call costs what a call inside the caller's `jax.jit` does; under a transformation it
  traces inline. The program's size does not grow with M (a `lax.scan` over groups of samples).

  Args:
    samples: `(M, H, W, K)` float softmax samples, one per dropout key / ensemble member.

  Returns:
    `(mean, var)`, both `(H, W, K)` float32. With M = 1 the variance is exactly zero.
  """
  shape = np.shape(samples)
  dtype = samples.dtype if hasattr(samples, "dtype") else np.result_type(samples)
  if len(shape) != 4:
    raise ValueError(f"mc_moments expects samples of shape (M, H, W, K); got shape {shape}")
  if not jnp.issubdtype(dtype, jnp.floating):
    raise TypeError(f"mc_moments expects float probabilities; got dtype {dtype}")
  if shape[0] == 0:
    raise ValueError("mc_moments needs at least one sample (M >= 1); got M = 0")
  return _moments(samples)


def _group_sums(samples: jax.Array, start, size: int) -> tuple[jax.Array, jax.Array]:
  """Σ d and Σ d² over samples[start : start + size] (static size), one fused elementwise pass."""
  first = samples[0]
  group_d = group_d2 = None
  for s in range(size):
    d = (samples[start + s] if isinstance(start, int)
         else jax.lax.dynamic_index_in_dim(samples, start + s, keepdims=False)) - first
    group_d = d if group_d is None else group_d + d
    group_d2 = d * d if group_d2 is None else group_d2 + d * d
  return group_d, group_d2


@jax.jit
def _moments(samples: jax.Array) -> tuple[jax.Array, jax.Array]:
  """`mc_moments`' arithmetic on checked `(M, H, W, K)` samples.

  Samples 1..M−1 are summed in groups of `_MOMENT_GROUP`: the full groups by a `lax.scan` (one
  compiled body whatever M is), the last partial group unrolled. The order of the additions is
  the same as one sequential loop over groups, so the result does not depend on M's split.
  """
  samples = jnp.asarray(samples).astype(jnp.float32)
  num = samples.shape[0]
  first = samples[0]
  full, tail = divmod(num - 1, _MOMENT_GROUP)
  sums = (jnp.zeros_like(first), jnp.zeros_like(first))

  def step(carry, g):
    group = _group_sums(samples, 1 + g * _MOMENT_GROUP, _MOMENT_GROUP)
    return (carry[0] + group[0], carry[1] + group[1]), None

  if full:
    sums, _ = jax.lax.scan(step, sums, jnp.arange(full))
  if tail:
    group = _group_sums(samples, 1 + full * _MOMENT_GROUP, tail)
    sums = (sums[0] + group[0], sums[1] + group[1])
  mean_d = sums[0] / num
  return first + mean_d, jnp.maximum(sums[1] / num - mean_d * mean_d, 0.0)


SegmentFn = Callable[[Any, jax.Array, jax.Array], jax.Array]
"""`segment_fn(params, key, image) -> samples (M, H, W, K)`: class-probability samples."""

ApplyFn = Callable[[Any, jax.Array, jax.Array], jax.Array]
"""`apply_fn(params, key, image) -> probs (H, W, K)`: one forward pass (stochastic in `key`
for MC dropout; deterministic networks ignore `key`)."""


class Prediction(NamedTuple):
  """Class probabilities of one frame (or a batch, with a leading B axis).

  Attributes:
    probs: `(H, W, K)` float32, the MC mean (or the single-pass softmax); `Frame.probs`.
    var: `(H, W, K)` float32 per-class epistemic variance, or None; `Frame.var`.
  """

  probs: jax.Array
  var: Optional[jax.Array] = None


@runtime_checkable
class ProbabilitySource(Protocol):
  """Anything that yields a frame's class probabilities.

  Network sources use `key` (dropout masks) and `image`, and ignore `index`; precomputed
  sources read frame `index` from disk and ignore `key` and `image`.
  """

  def predict(self, key: Optional[jax.Array], image: Any, *,
              index: Optional[int] = None) -> Prediction:
    ...


def _check_samples(samples, where: str):
  if samples.ndim != 4:
    raise ValueError(f"{where} must return samples of shape (M, H, W, K); got {samples.shape}")
  if not jnp.issubdtype(samples.dtype, jnp.floating):
    raise TypeError(f"{where} must return float probabilities; got dtype {samples.dtype}")


@functools.partial(jax.jit, static_argnames=("segment_fn", "with_variance"))
def _predict(params, key, image, *, segment_fn, with_variance):
  samples = segment_fn(params, key, image)
  _check_samples(samples, "segment_fn")
  if with_variance:
    return Prediction(*mc_moments(samples))
  return Prediction(jnp.mean(samples.astype(jnp.float32), axis=0), None)


@functools.partial(jax.jit, static_argnames=("segment_fn", "with_variance"))
def _predict_batch(params, key, images, *, segment_fn, with_variance):
  keys = jax.random.split(key, images.shape[0])
  return jax.vmap(
      lambda k, im: _predict(params, k, im, segment_fn=segment_fn, with_variance=with_variance)
  )(keys, images)


@dataclasses.dataclass(frozen=True)
class NetworkSource:
  """A `ProbabilitySource` computed by a JAX network: a `segment_fn` and its parameters.

  `predict` is one jitted call (compiled once per image shape). `segment_fn` is a static
  argument of that jit, so reuse one source rather than rebuilding it per frame.

  Attributes:
    segment_fn: `(params, key, image) -> samples (M, H, W, K)`.
    params: the pytree passed to `segment_fn` as its first argument.
    with_variance: return `mc_moments` of the samples (True) or only their mean, var None.
  """

  segment_fn: SegmentFn
  params: Any
  with_variance: bool = True

  def predict(self, key: Optional[jax.Array], image: Any, *,
              index: Optional[int] = None) -> Prediction:
    """Class probabilities of one image.

    Args:
      key: PRNG key (dropout masks); None is allowed only for deterministic sources.
      image: whatever `segment_fn` takes, e.g. `(H, W, 3)` uint8 RGB.
      index: ignored (frame index, used by precomputed sources).

    Returns:
      `Prediction(probs (H, W, K), var (H, W, K) or None)`, float32.
    """
    del index
    key = self._key(key)
    return _predict(self.params, key, image, segment_fn=self.segment_fn,
                    with_variance=self.with_variance)

  def predict_batch(self, key: Optional[jax.Array], images: Any) -> Prediction:
    """`predict` over a leading frame axis in one jitted call (frame b uses `split(key, B)[b]`).

    Args:
      key: PRNG key.
      images: `(B, ...)` stack of images.

    Returns:
      `Prediction(probs (B, H, W, K), var (B, H, W, K) or None)`.
    """
    return _predict_batch(self.params, self._key(key), images, segment_fn=self.segment_fn,
                          with_variance=self.with_variance)

  def _key(self, key):
    if key is None:
      if self.with_variance:
        raise ValueError("this source samples (MC dropout / stochastic segment_fn): pass a "
                         "PRNG key, e.g. jax.random.key(0)")
      return jax.random.key(0)  # Deterministic source: the key is unused.
    return key


def segment_fn_source(segment_fn: SegmentFn, params: Any, *,
                      with_variance: bool = True) -> NetworkSource:
  """The general adapter: any `segment_fn(params, key, image) -> samples (M, H, W, K)`.

  Args:
    segment_fn: returns M class-probability samples of one image (M = 1 is allowed).
    params: its parameters.
    with_variance: compute the epistemic variance with `mc_moments` (False: var is None).
  """
  return NetworkSource(segment_fn, params, with_variance)


def mc_dropout_source(apply_fn: ApplyFn, params: Any, *, num_samples: int = 32
                      ) -> NetworkSource:
  """MC dropout: M stochastic passes under one `jax.vmap` over M dropout keys.

  Args:
    apply_fn: `(params, key, image) -> probs (H, W, K)` with dropout active (random in `key`).
    params: its parameters.
    num_samples: M (32 in the paper).

  Returns:
    A source whose `predict` gives the MC mean and the per-class variance.
  """
  if num_samples < 1:
    raise ValueError(f"num_samples must be >= 1; got {num_samples}")

  def segment_fn(p, key, image):
    keys = jax.random.split(key, num_samples)
    return jax.vmap(lambda k: apply_fn(p, k, image))(keys)

  return NetworkSource(segment_fn, params, True)


def deterministic_source(apply_fn: ApplyFn, params: Any) -> NetworkSource:
  """One deterministic pass (dropout off; the baselines). `var` is None.

  Args:
    apply_fn: `(params, key, image) -> probs (H, W, K)`; should not depend on `key`.
    params: its parameters.
  """

  def segment_fn(p, key, image):
    return apply_fn(p, key, image)[None]

  return NetworkSource(segment_fn, params, False)


def ensemble_source(apply_fn: ApplyFn, params_list: Sequence[Any]) -> NetworkSource:
  """A deep ensemble: one pass per member; mean and variance across members.

  The members' parameters are stacked on a new leading axis and the passes `vmap`ped, so one
  compiled call serves the whole ensemble. Each member gets its own key (relevant only if
  `apply_fn` is stochastic).

  Args:
    apply_fn: `(params, key, image) -> probs (H, W, K)`.
    params_list: E >= 1 parameter pytrees of identical structure and shapes.
  """
  params_list = list(params_list)
  if not params_list:
    raise ValueError("ensemble_source needs at least one member")
  structure = jax.tree_util.tree_structure(params_list[0])
  shapes = [np.shape(leaf) for leaf in jax.tree_util.tree_leaves(params_list[0])]
  for i, member in enumerate(params_list[1:], start=1):
    if (jax.tree_util.tree_structure(member) != structure or
        [np.shape(leaf) for leaf in jax.tree_util.tree_leaves(member)] != shapes):
      raise ValueError(f"ensemble member {i} has a different parameter structure or shapes "
                       "than member 0; all members must share one architecture")
  stacked = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *params_list)
  num_members = len(params_list)

  def segment_fn(p, key, image):
    keys = jax.random.split(key, num_members)
    return jax.vmap(lambda member, k: apply_fn(member, k, image))(p, keys)

  return NetworkSource(segment_fn, stacked, True)


_PROB_TOL = 1e-3


def _as_float(name, array, path):
  array = np.asarray(array)
  if not np.issubdtype(array.dtype, np.floating):
    raise io.BadFileError(f"{path}: '{name}' must be float probabilities; got dtype "
                          f"{array.dtype}")
  if not np.all(np.isfinite(array)):
    raise io.BadFileError(f"{path}: '{name}' has NaN or infinite values")
  return array.astype(np.float32)


def _check_distribution(probs, name, path):
  if probs.min(initial=0.0) < -_PROB_TOL or probs.max(initial=0.0) > 1 + _PROB_TOL:
    raise ValueError(f"{path}: '{name}' must be probabilities in [0, 1] (apply softmax to "
                     f"logits before saving); got range [{probs.min()}, {probs.max()}]")
  total = probs.sum(-1)
  if np.max(np.abs(total - 1.0), initial=0.0) > 1e-2:
    raise ValueError(f"{path}: '{name}' must sum to 1 over the last (class) axis; sums range "
                     f"over [{total.min()}, {total.max()}] (channels-first arrays need "
                     "channels_first=True)")


class PrecomputedFrame(NamedTuple):
  """One frame of a `PrecomputedSource`, as stored (`PrecomputedSource.read`).

  Attributes:
    samples: `(M, H, W, K) float32` samples, or None when the file holds moments.
    probs: `(H, W, K) float32` MC mean, or None when the file holds samples.
    var: `(H, W, K) float32` variance, or None.
    extra: the file's other arrays by name (e.g. `det`), unchecked.
  """
  samples: Optional[np.ndarray]
  probs: Optional[np.ndarray]
  var: Optional[np.ndarray]
  extra: dict


@dataclasses.dataclass(frozen=True)
class PrecomputedSource:
  """Predictions read from disk: one `.npz` per frame, frames in sorted file-name order.

  Each file holds either `mean` `(H, W, K)` (and optionally `var` `(H, W, K)`) or `samples`
  `(M, H, W, K)` (moments computed with `mc_moments`). Arrays are float class probabilities
  (after softmax); with `channels_first=True` they are `(K, H, W)` / `(M, K, H, W)` as a
  PyTorch network produces them, and are transposed on reading.

  Attributes:
    files: the frame files in frame order.
    channels_first: stored arrays are `(..., K, H, W)`.
  """

  files: tuple[pathlib.Path, ...]
  channels_first: bool = False

  def __len__(self) -> int:
    return len(self.files)

  def predict(self, key: Optional[jax.Array], image: Any, *,
              index: Optional[int] = None) -> Prediction:
    """Reads frame `index`.

    Args:
      key: ignored.
      image: None, or an image whose H×W must match the stored prediction's.
      index: frame number in `[0, len(self))` (required).

    Returns:
      `Prediction(probs (H, W, K), var (H, W, K) or None)` float32 arrays.
    """
    del key
    frame = self.read(index)
    if frame.samples is not None:
      probs, var = (np.asarray(a) for a in mc_moments(frame.samples))
    else:
      probs, var = frame.probs, frame.var
    if image is not None and tuple(np.shape(image)[:2]) != probs.shape[:2]:
      raise ValueError(f"{self.files[index]}: prediction is {probs.shape[:2]} pixels but the "
                       f"image is {tuple(np.shape(image)[:2])}")
    return Prediction(jnp.asarray(probs), None if var is None else jnp.asarray(var))

  def read(self, index: int) -> "PrecomputedFrame":
    """Frame `index` as stored, checked, from one read of its file: its samples, or its
    moments, and any other arrays it holds (e.g. a dropout-off pass `det`)."""
    path, contents = self._read(index)
    extra = {k: v for k, v in contents.items() if k not in ("samples", "mean", "var")}
    if "samples" in contents:
      return PrecomputedFrame(self._samples(path, contents), None, None, extra)
    if "mean" not in contents:
      raise ValueError(f"{path}: expected arrays 'mean' (+ optional 'var') or 'samples'; "
                       f"found {sorted(contents)}")
    probs = _as_float("mean", contents["mean"], path)
    var = _as_float("var", contents["var"], path) if "var" in contents else None
    if self.channels_first:
      probs = np.moveaxis(probs, 0, -1) if probs.ndim == 3 else probs
      var = np.moveaxis(var, 0, -1) if var is not None and var.ndim == 3 else var
    if probs.ndim != 3:
      raise ValueError(f"{path}: 'mean' must have shape (H, W, K); got {probs.shape}")
    _check_distribution(probs, "mean", path)
    if var is not None:
      if var.shape != probs.shape:
        raise ValueError(f"{path}: 'var' {var.shape} must match 'mean' {probs.shape}")
      if var.min(initial=0.0) < 0:
        raise ValueError(f"{path}: 'var' must be non-negative")
    return PrecomputedFrame(None, probs, var, extra)

  def read_samples(self, index: int) -> Optional[np.ndarray]:
    """The checked `(M, H, W, K)` float32 samples of frame `index`, or None when its file holds
    moments (`mean`, `var`) instead."""
    return self.read(index).samples

  def _read(self, index: Optional[int]) -> tuple:
    if index is None:
      raise ValueError("a precomputed source needs the frame number: predict(..., index=i)")
    if not -len(self.files) <= index < len(self.files):
      raise IndexError(f"frame {index} out of range: {len(self.files)} precomputed frames")
    path = self.files[index]
    contents = io.read_npz(str(path), what="precomputed prediction file")
    if "samples" in contents and "mean" in contents:
      raise ValueError(f"{path}: holds both 'samples' and 'mean'; keep one")
    return path, contents

  def _samples(self, path, contents) -> np.ndarray:
    samples = _as_float("samples", contents["samples"], path)
    if self.channels_first and samples.ndim == 4:
      samples = np.moveaxis(samples, 1, -1)
    if samples.ndim != 4:
      raise ValueError(f"{path}: 'samples' must have shape (M, H, W, K); got {samples.shape}")
    _check_distribution(samples, "samples", path)
    return samples


def precomputed_source(directory: str | os.PathLike, *, pattern: str = "*.npz",
                       channels_first: bool = False) -> PrecomputedSource:
  """Predictions saved by any network (PyTorch included), one `.npz` per frame.

  Write frame i as e.g. `np.savez(f"{dir}/{i:06d}.npz", mean=probs_hwk, var=var_hwk)` or
  `np.savez(..., samples=samples_mhwk)` (see `save_prediction`); zero-pad the numbers so
  that sorted file names are in frame order.

  Args:
    directory: folder of `.npz` files.
    pattern: glob selecting the frame files.
    channels_first: arrays are stored `(K, H, W)` / `(M, K, H, W)`.

  Raises:
    FileNotFoundError: the folder does not exist or has no matching files.
  """
  directory = pathlib.Path(directory)
  if not directory.is_dir():
    raise FileNotFoundError(f"no directory of precomputed predictions at {directory}")
  files = tuple(sorted(directory.glob(pattern)))
  if not files:
    raise FileNotFoundError(f"no files matching {pattern!r} in {directory}")
  return PrecomputedSource(files, channels_first)


def save_prediction(path: str | os.PathLike, *, mean=None, var=None, samples=None
                    ) -> pathlib.Path:
  """Writes one frame in the `precomputed_source` format (`.npz`, float32).

  Args:
    path: destination file.
    mean: `(H, W, K)` probabilities (with optional `var`), or
    var: `(H, W, K)` epistemic variance (needs `mean`).
    samples: `(M, H, W, K)` probability samples (instead of `mean`/`var`).

  Returns:
    The path written.
  """
  if (samples is None) == (mean is None):
    raise ValueError("give either `samples` or `mean` (with optional `var`)")
  if var is not None and mean is None:
    raise ValueError("`var` needs `mean`")
  arrays = ({"samples": samples} if samples is not None else
            {"mean": mean, **({"var": var} if var is not None else {})})
  path = pathlib.Path(path)
  if path.suffix != ".npz":
    raise ValueError(f"precomputed frames are .npz files; got {path}")
  arrays = {k: np.asarray(v, np.float32) for k, v in arrays.items()}
  io.atomic_write(str(path), lambda tmp: np.savez(tmp, **arrays))
  return path
