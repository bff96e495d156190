"""The shipped learned-rule parameters (the first learned rule and the rule family's fit): they
load as a rule, match their record, were fitted on layouts no command judges on, and fuse to
finite maps."""

import json
import re

import numpy as np
import pytest

import jaxfusion as jf
import jaxfusion_models
from jaxfusion.lab import learning
from tests import engine_helpers as h


def _record(path=None):
  with open(path or jaxfusion_models.LEARNED_RULE_RECORD, encoding="utf-8") as f:
    return json.load(f)


def test_shipped_parameters_load_and_match_their_record():
  rule = jaxfusion_models.load_learned_rule()
  assert rule.name == "learned" and rule.requires_var
  params = jf.learn.load_params(str(jaxfusion_models.LEARNED_RULE_PATH))
  record = _record()
  assert record["params"] == params
  assert jaxfusion_models.load_learned_rule(aggregate="mean").aggregate == "mean"


def test_shipped_family_rule_loads_and_matches_its_record():
  rule = jaxfusion_models.load_family_rule()
  family, params = jf.learn.load_rule(str(jaxfusion_models.FAMILY_RULE_PATH))
  record = _record(jaxfusion_models.FAMILY_RULE_RECORD)
  assert family == "family" and rule.name == "family" and rule.requires_var
  assert record["params"] == params and record["family"] == "family"
  assert np.shape(params["spatial"]) == (7, 3) and np.shape(params["table"])[0] == 7
  assert "--family family" in record["command"] and "--start-table" in record["command"]
  assert record["select"] == "miou"
  assert jaxfusion_models.load_family_rule(aggregate="mean").aggregate == "mean"
  # The map made for it keeps its spatial kernel, so every read-out is smoothed (§4.1).
  state = jf.init_map(capacity=64, num_classes=7, voxel_size=0.1, rule=rule)
  np.testing.assert_array_equal(np.asarray(state.spatial), np.asarray(params["spatial"],
                                                                      np.float32))


@pytest.mark.parametrize("record_path", ["LEARNED_RULE_RECORD", "FAMILY_RULE_RECORD"])
def test_shipped_parameters_never_saw_a_judged_layout(record_path):
  record = _record(getattr(jaxfusion_models, record_path))
  names = record["data"]["train"] + record["data"]["validation"]
  seeds = {int(re.search(r"_s(\d+)$", n).group(1)) for n in names}
  assert seeds and not seeds & set(learning.JUDGED_SEEDS), seeds
  train = {re.search(r"_s(\d+)$", n).group(1) for n in record["data"]["train"]}
  val = {re.search(r"_s(\d+)$", n).group(1) for n in record["data"]["validation"]}
  assert not train & val
  assert record["command"].startswith("jaxfusion learn-rule")
  assert record["seconds"]["total"] < 45 * 60          # the recipe fits on 2 CPU cores


@pytest.mark.parametrize("load", h.main_tier_keeps(["load_learned_rule", "load_family_rule"],
                                                    ("load_family_rule",)))
def test_shipped_rule_fuses_hard_frames_to_finite_maps(load):
  rng = np.random.default_rng(0)
  k, rows, cols = 7, 6, 8
  probs = rng.dirichlet(np.ones(k), (rows, cols)).astype(np.float32)
  probs[0, 0] = np.eye(k)[2]                            # exactly 0 and 1
  var = np.zeros((rows, cols, k), np.float32)           # zero variance
  var[1] = 0.25
  depth = np.full((rows, cols), 2.0, np.float32)
  depth[2, :3] = 0.0                                    # holes
  rule = getattr(jaxfusion_models, load)()
  state = jf.init_map(capacity=256, num_classes=k, voxel_size=0.1, rule=rule)
  cam = jf.Camera(8.0, 8.0, 3.5, 2.5)
  for _ in range(3):
    state = jf.fuse_frame(state, jf.Frame(depth, np.eye(4, dtype=np.float32), probs, var), cam,
                          rule)
  out = jf.read_map(state)
  assert len(out["labels"]) > 0
  for leaf in jax_leaves(out):
    assert np.all(np.isfinite(leaf))


def jax_leaves(tree):
  return [np.asarray(v) for v in tree.values() if np.asarray(v).dtype.kind == "f"]
