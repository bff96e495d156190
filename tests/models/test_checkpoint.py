"""Checkpoints: exact round trip, refusal of mismatched class lists / architectures, messages."""

import dataclasses

import jax
import numpy as np
import pytest

from models import checkpoint, net

K = 7


@pytest.fixture(scope="module")
def tiny():
  config = net.tiny_config(K)
  # Any weights do; an RBG key compiles the initialiser in a fraction of threefry's time.
  graphdef, params = net.init(config, key=jax.random.key(0, impl="rbg"))
  return config, graphdef, params


def test_round_trip_is_bit_exact(tmp_path, tiny):
  config, _, params = tiny
  path = checkpoint.save(tmp_path / "m.msgpack", params, config=config,
                         class_names=net.DEFAULT_CLASS_NAMES, record={"seed": 3})
  loaded = checkpoint.load(path, class_names=net.DEFAULT_CLASS_NAMES, config=config)
  assert loaded.config == config
  assert loaded.class_names == net.DEFAULT_CLASS_NAMES
  assert loaded.metadata["record"] == {"seed": 3}
  assert (jax.tree_util.tree_structure(loaded.params) ==
          jax.tree_util.tree_structure(params))
  before, after = checkpoint.flatten_params(params), checkpoint.flatten_params(loaded.params)
  assert before.keys() == after.keys()
  for name in before:
    assert before[name].dtype == after[name].dtype
    np.testing.assert_array_equal(before[name], after[name])
  # Saving the loaded model again gives the same bytes.
  again = checkpoint.save(tmp_path / "again.msgpack", loaded.params, config=config,
                          class_names=net.DEFAULT_CLASS_NAMES, record={"seed": 3})
  assert again.read_bytes() == path.read_bytes()


def test_loaded_model_predicts_like_the_original(tmp_path, tiny):
  from models import sampling
  config, graphdef, params = tiny
  path = checkpoint.save(tmp_path / "m.msgpack", params, config=config,
                         class_names=net.DEFAULT_CLASS_NAMES)
  loaded = checkpoint.load(path)
  image = np.random.default_rng(0).integers(0, 256, (16, 16, 3), dtype=np.uint8)
  np.testing.assert_array_equal(
      np.asarray(sampling.deterministic_probs(graphdef, params, image)),
      np.asarray(sampling.deterministic_probs(loaded.graphdef, loaded.params, image)))


def test_refuses_other_class_list(tmp_path, tiny):
  config, _, params = tiny
  path = checkpoint.save(tmp_path / "m.msgpack", params, config=config,
                         class_names=net.DEFAULT_CLASS_NAMES)
  names = net.DEFAULT_CLASS_NAMES[::-1]
  with pytest.raises(checkpoint.CheckpointError, match="python -m models.train"):
    checkpoint.load(path, class_names=names)


def test_refuses_other_architecture(tmp_path, tiny):
  config, _, params = tiny
  path = checkpoint.save(tmp_path / "m.msgpack", params, config=config,
                         class_names=net.DEFAULT_CLASS_NAMES)
  other = dataclasses.replace(config, aspp_width=16)
  with pytest.raises(checkpoint.CheckpointError, match="aspp_width"):
    checkpoint.load(path, config=other)


def test_refuses_params_that_do_not_fit_the_config(tmp_path, tiny):
  config, _, params = tiny
  other = dataclasses.replace(config, aspp_width=16)
  with pytest.raises(checkpoint.CheckpointError, match="shape"):
    checkpoint.save(tmp_path / "m.msgpack", params, config=other,
                    class_names=net.DEFAULT_CLASS_NAMES)
  with pytest.raises(ValueError, match="class names"):
    checkpoint.save(tmp_path / "m.msgpack", params, config=config, class_names=("a", "b"))


def test_missing_or_corrupt_file_says_what_to_run(tmp_path):
  with pytest.raises(FileNotFoundError, match="python -m models.train"):
    checkpoint.load(tmp_path / "absent.msgpack")
  bad = tmp_path / "bad.msgpack"
  bad.write_bytes(b"not a checkpoint")
  with pytest.raises(checkpoint.CheckpointError, match="python -m models.train"):
    checkpoint.load(bad)
