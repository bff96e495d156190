"""Saving and loading `SegNet` checkpoints (one msgpack file, `flax.serialization`).

A checkpoint is a single `.msgpack` file holding a format tag, JSON metadata (the
architecture `SegNetConfig`, the class names in label order, and a free-form training record),
the parameters as a flat `{path: ndarray}` map, and a digest of both (msgpack has no checksum of
its own; checkpoints written before the digest load without one). Loading rebuilds the
architecture from the stored config, checks every parameter's path, shape and dtype against it,
and refuses a checkpoint whose class list or architecture differs from what the caller expects,
with a message that says what to run. Round trips are bit-exact.
"""

import dataclasses
import json
import os
import pathlib
from typing import Any, NamedTuple, Sequence

import jax
import numpy as np
from flax import nnx, serialization

from jaxfusion import io as jf_io

from . import net

FORMAT = "jaxfusion_models.segnet"
FORMAT_VERSION = 1
WEIGHTS_DIR = pathlib.Path(__file__).resolve().parent / "weights"
PRETRAINED_PATH = WEIGHTS_DIR / "segnet.msgpack"
TRAIN_COMMAND = "python -m models.train"


class CheckpointError(ValueError):
  """A checkpoint that is unreadable or does not match what the caller expects."""


class LoadedModel(NamedTuple):
  """A network ready for `sampling`: static graph, parameters and their description.

  Attributes:
    config: the architecture.
    graphdef: static NNX graph (pass as a static argument).
    params: `nnx.State` of float32 parameters.
    class_names: K class names in label order.
    metadata: the whole stored metadata (config, class names, training record).
  """

  config: net.SegNetConfig
  graphdef: nnx.GraphDef
  params: nnx.State
  class_names: tuple[str, ...]
  metadata: dict[str, Any]


def _path_str(path) -> str:
  parts = []
  for entry in path:
    if isinstance(entry, jax.tree_util.DictKey):
      parts.append(str(entry.key))
    elif isinstance(entry, jax.tree_util.GetAttrKey):
      parts.append(entry.name)
    elif isinstance(entry, jax.tree_util.SequenceKey):
      parts.append(str(entry.idx))
    else:
      parts.append(str(entry))
  return "/".join(parts)


def flatten_params(params: nnx.State) -> dict[str, np.ndarray]:
  """`{"aspp/atrous/0/conv/kernel/value": ndarray, ...}` — host copies of every leaf."""
  return {_path_str(path): np.asarray(leaf)
          for path, leaf in jax.tree_util.tree_leaves_with_path(params)}


def save(path: str | os.PathLike, params: nnx.State, *, config: net.SegNetConfig,
         class_names: Sequence[str], record: dict[str, Any] | None = None) -> pathlib.Path:
  """Writes a checkpoint atomically (temporary file, then rename).

  Args:
    path: destination `.msgpack` file; parent folders are created.
    params: the network parameters (must match `config`).
    config: the architecture that produced `params`.
    class_names: K names in label order; `len(class_names) == config.num_classes`.
    record: free-form JSON-serialisable training record (command, seed, data, accuracy).

  Returns:
    The path written.
  """
  class_names = tuple(str(c) for c in class_names)
  if len(class_names) != config.num_classes:
    raise ValueError(
        f"{len(class_names)} class names for a network with {config.num_classes} classes")
  _check_params(flatten_params(params), config, source="params to save")
  metadata = {"config": config.to_dict(), "class_names": list(class_names),
              "record": record or {}}
  payload = {
      "format": FORMAT,
      "format_version": FORMAT_VERSION,
      "metadata": json.dumps(metadata, sort_keys=True),
      "params": flatten_params(params),
  }
  payload["digest"] = _digest(payload["metadata"], payload["params"])
  path = pathlib.Path(path)
  data = serialization.msgpack_serialize(payload)
  jf_io.atomic_write(str(path), lambda tmp: pathlib.Path(tmp).write_bytes(data))
  return path


def _digest(metadata: str, flat: dict[str, np.ndarray]) -> str:
  """SHA-256 of a checkpoint's metadata and parameters: msgpack itself has no checksum."""
  return jf_io.array_digest({"metadata": np.frombuffer(metadata.encode(), np.uint8), **flat})


def _check_params(flat: dict[str, np.ndarray], config: net.SegNetConfig, *, source: str):
  _, abstract = net.abstract_params(config)
  expected = {_path_str(p): leaf for p, leaf in jax.tree_util.tree_leaves_with_path(abstract)}
  missing = sorted(set(expected) - set(flat))
  extra = sorted(set(flat) - set(expected))
  if missing or extra:
    raise CheckpointError(
        f"{source}: parameters do not match the architecture {config}: "
        f"missing {missing[:5]}{'...' if len(missing) > 5 else ''}, "
        f"unexpected {extra[:5]}{'...' if len(extra) > 5 else ''}")
  for name, leaf in expected.items():
    got = flat[name]
    if tuple(got.shape) != tuple(leaf.shape) or got.dtype != leaf.dtype:
      raise CheckpointError(
          f"{source}: parameter {name} has shape {got.shape} {got.dtype}, the architecture "
          f"needs {leaf.shape} {leaf.dtype}")
  return abstract


def load(path: str | os.PathLike, *, class_names: Sequence[str] | None = None,
         config: net.SegNetConfig | None = None) -> LoadedModel:
  """Reads a checkpoint and rebuilds the network, refusing mismatches.

  Args:
    path: a `.msgpack` file written by `save`.
    class_names: if given, the checkpoint's class list must equal it (same order).
    config: if given, the checkpoint's architecture must equal it.

  Returns:
    A `LoadedModel`; its parameters equal the saved ones bit for bit.

  Raises:
    FileNotFoundError: no file at `path` (the message says how to train one).
    CheckpointError: unreadable file, other format, or class list / architecture mismatch.
  """
  path = pathlib.Path(path)
  if not path.is_file():
    raise FileNotFoundError(
        f"no checkpoint at {path}. Train one with `{TRAIN_COMMAND} --out {path}` "
        f"(or `{TRAIN_COMMAND} --quick --out {path}` for a fast, rough model).")
  try:
    payload = serialization.msgpack_restore(path.read_bytes())
    fmt, version = payload["format"], payload["format_version"]
    metadata = json.loads(payload["metadata"])
    flat = {k: np.asarray(v) for k, v in payload["params"].items()}
    # Checkpoints written before the digest was added have none; they still load.
    if "digest" in payload and payload["digest"] != _digest(payload["metadata"], flat):
      raise ValueError("its parameters or metadata do not match their digest (damaged)")
  except Exception as e:  # Any parse failure means the file is not one of ours.
    raise CheckpointError(
        f"{path} is not a readable jaxfusion_models checkpoint ({type(e).__name__}: {e}). "
        f"Re-create it with `{TRAIN_COMMAND} --out {path}`.") from e
  if fmt != FORMAT or version != FORMAT_VERSION:
    raise CheckpointError(
        f"{path} has format {fmt!r} v{version}; this code reads {FORMAT!r} v{FORMAT_VERSION}. "
        f"Re-create it with `{TRAIN_COMMAND} --out {path}`.")
  try:
    stored_config = net.SegNetConfig.from_dict(metadata["config"])
    stored_names = tuple(str(c) for c in metadata["class_names"])
    if not isinstance(metadata.get("record", {}), dict):
      raise ValueError("its training record is not a JSON object")
    if len(stored_names) != stored_config.num_classes:
      raise ValueError(f"{len(stored_names)} class names for {stored_config.num_classes} "
                       "classes")
  except Exception as e:  # A damaged metadata block: any failure means it is not ours.
    raise CheckpointError(
        f"{path} is not a readable jaxfusion_models checkpoint (bad metadata: "
        f"{type(e).__name__}: {e}). Re-create it with `{TRAIN_COMMAND} --out {path}`.") from e
  if class_names is not None and tuple(class_names) != stored_names:
    raise CheckpointError(
        f"{path} was trained for classes {stored_names}, but {tuple(class_names)} were "
        f"expected. Train a matching model with `{TRAIN_COMMAND} --out {path}`.")
  if config is not None and config != stored_config:
    diff = {f.name: (getattr(stored_config, f.name), getattr(config, f.name))
            for f in dataclasses.fields(config)
            if getattr(stored_config, f.name) != getattr(config, f.name)}
    raise CheckpointError(
        f"{path} has a different architecture; differing fields (stored, expected): {diff}. "
        f"Train a matching model with `{TRAIN_COMMAND} --out {path}` or load without `config`.")
  abstract = _check_params(flat, stored_config, source=str(path))
  treedef = jax.tree_util.tree_structure(abstract)
  names = [_path_str(p) for p, _ in jax.tree_util.tree_leaves_with_path(abstract)]
  params = jax.tree_util.tree_unflatten(treedef, [jax.numpy.asarray(flat[n]) for n in names])
  graphdef, _ = net.abstract_params(stored_config)
  return LoadedModel(stored_config, graphdef, params, stored_names, metadata)


def load_pretrained(*, class_names: Sequence[str] | None = net.DEFAULT_CLASS_NAMES
                    ) -> LoadedModel:
  """Loads the shipped weights (`models/weights/segnet.msgpack`), checking the class list.

  Args:
    class_names: the classes the caller's data uses (default: the embedded world's seven);
      None skips the check.
  """
  return load(PRETRAINED_PATH, class_names=class_names)
