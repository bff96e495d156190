"""The rule family (docs/equations.md §3.11): every Bayesian rule shipped as a member, the same
maps bit for bit where the same operations are computed; random members against the NumPy
reference; terms a rule lacks cost nothing (the same program as the rule it equals); finite maps
on hard inputs and huge weights; de-integration; one clear line for bad parameters."""

import importlib

import hypothesis
import hypothesis.strategies as st
import jax
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import context
from jaxfusion import deintegration
from tests import context_reference
from tests import engine_helpers as h
from tests.reference import ReferenceMap

learned_lib = importlib.import_module("jaxfusion.rules.learned")
family_lib = jf.rules.family_lib
K = h.NUM_CLASSES
VOXEL = 0.25


def _frames(seed, n=3, rgb=True):
  rng = np.random.default_rng(seed)
  out = []
  for _ in range(n):
    f = h.random_frame(rng, voxel_size=VOXEL)
    # Depths of the study's range, so that every depth bin of the table is used.
    depth = np.where(np.isfinite(f.depth) & (f.depth > 0), f.depth * 3.0, f.depth)
    depth = h.drop_ambiguous_pixels(depth.astype(np.float32), f.T_world_cam, h.CAMERA, VOXEL)
    image = rng.integers(0, 256, depth.shape + (3,), dtype=np.uint8) if rgb else None
    out.append(f._replace(depth=depth, rgb=image))
  return out


def _fuse(rule, frames, capacity=2048):
  state = jf.init_map(capacity=capacity, num_classes=K, voxel_size=VOXEL, rule=rule)
  for f in frames:
    state = jf.fuse_frame(state, f, h.CAMERA, rule)
  return state


def _same(a, b):
  np.testing.assert_array_equal(np.asarray(a.keys), np.asarray(b.keys))
  assert sorted(a.rows) == sorted(b.rows)
  for name in a.rows:
    np.testing.assert_array_equal(np.asarray(a.rows[name]), np.asarray(b.rows[name]), name)


def _table(rng):
  return rng.uniform(0.1, 3.0, (K, len(jf.rules.glfs_lib.DEPTH_EDGES) + 1,
                                len(jf.rules.glfs_lib.ANGLE_EDGES) + 1)).astype(np.float32)


def _member_and_rule(case, rng):
  """`(family member, the rule it must equal bit for bit)` for a shipped rule."""
  if case == "glfs":
    glfs = jf.rules.glfs(_table(rng))
    member = family_lib.of_glfs(glfs)
    assert family_lib.terms(member) == ("table",)
    return member, glfs
  if case == "bayes":
    return jf.rules.family(), jf.rules.bayes()
  if case == "robust_r":
    beta = rng.uniform(0.05, 0.5, K)
    return jf.rules.family({"beta": beta}), jf.rules.robust(beta=beta, dirichlet=False)
  if case == "learned":
    v1 = jf.rules.learned({"theta": rng.normal(0, 1, 6), "bias": 1.0, "mix": 0.6,
                           "gate": [2.0, -1.0, 0.5], "beta": rng.uniform(0, 0.5, K)})
    return family_lib.of_learned(v1), v1
  names = ("depth", "label_edge", "luminance")      # a learned rule with context
  v2 = jf.rules.learned({"theta": rng.normal(0, 1, (K, 6)), "bias": rng.normal(0, 1, K),
                         "context_theta": rng.normal(0, 1, (K, 3)), "mix": 0.3,
                         "gate": [1.0, 0.5, -0.5, 0.3, -0.2], "beta": 0.2}, context=names)
  member = family_lib.of_learned(v2)
  assert member.context == names and member.remove is None
  return member, v2


@pytest.mark.parametrize("case", h.main_tier_keeps(
    ["glfs", "bayes", "robust_r", "learned", "learned_context"], ("glfs", "learned_context")))
def test_shipped_rules_are_members_bit_for_bit(case):
  assert jf.rules.display_name(jf.rules.family()) == "Family"
  member, rule = _member_and_rule(case, np.random.default_rng(0))
  frames = _frames(1)
  _same(_fuse(member, frames), _fuse(rule, frames))


@pytest.mark.parametrize("name", h.main_tier_keeps(["robust_d", "robust_dr"], ("robust_dr",)))
def test_dirichlet_rules_are_members(name):
  frames = _frames(3)
  beta = 0.3 if name == "robust_dr" else None
  ours = _fuse(jf.rules.family({"mix": 1.0, **({} if beta is None else {"beta": beta})}), frames)
  paper = _fuse(jf.rules.by_name(name), frames)
  np.testing.assert_array_equal(np.asarray(ours.keys), np.asarray(paper.keys))
  # The same terms as the learned rule's special cases: float32 rounding of `0·a + b`.
  np.testing.assert_allclose(np.asarray(ours.rows["logp"]), np.asarray(paper.rows["logp"]),
                             rtol=1e-6, atol=1e-6)
  np.testing.assert_array_equal(np.asarray(ours.rows["alpha_bar"]),
                                np.asarray(paper.rows["alpha_bar"]))


def _program(rule, frame):
  state = jf.init_map(capacity=256, num_classes=K, voxel_size=VOXEL, rule=rule)
  text = str(jax.make_jaxpr(jf.fusion.fuse_frame_unchecked)(state, frame, h.CAMERA, rule))
  return text


def test_terms_a_rule_lacks_cost_nothing():
  rng = np.random.default_rng(4)
  frame = _frames(4, n=1, rgb=False)[0]
  glfs = jf.rules.glfs(_table(rng))
  assert _program(family_lib.of_glfs(glfs), frame) == _program(glfs, frame)
  assert _program(jf.rules.family(), frame._replace(var=None)) == _program(
      jf.rules.bayes(), frame._replace(var=None))
  # Adding a term changes the program (the comparison can fail).
  assert _program(jf.rules.family({"table": _table(rng), "moment_weights": np.zeros(6)}),
                  frame) != _program(glfs, frame)


def _reference(rule, params, frames):
  c = h.CAMERA
  ref = ReferenceMap("family", K, VOXEL, alpha0=float(params.get("alpha0", 1.5)),
                     aggregate=rule.aggregate,
                     learned={k: v for k, v in rule.hparams.items()}, context=rule.context)
  for f in frames:
    ctx = (context_reference.context(np.asarray(f.depth), np.asarray(f.probs),
                                     (c.fx, c.fy, c.cx, c.cy), rule.context, f.rgb)
           if rule.context else None)
    ref.fuse(np.asarray(f.depth), np.asarray(f.T_world_cam), np.asarray(f.probs),
             np.asarray(f.var), c.fx, c.fy, c.cx, c.cy, ctx=ctx)
  return ref.read()


def _compare(rule, params, frames):
  ours = jf.read_map(_fuse(rule, frames))
  want = _reference(rule, params, frames)
  order = np.lexsort(np.asarray(ours["coords"]).T[::-1])
  np.testing.assert_array_equal(np.asarray(ours["coords"])[order], want["coords"])
  assert len(want["coords"]) > 20
  np.testing.assert_allclose(np.asarray(ours["posterior"])[order], want["posterior"],
                             atol=2e-5, rtol=1e-4)


@pytest.mark.parametrize("aggregate", h.main_tier_keeps(["sum", "mean"], ("mean",)))
def test_every_term_at_once_matches_reference(aggregate):
  rng = np.random.default_rng(5)
  names = ("label_edge", "depth", "sharpness")
  params = {"table": _table(rng), "moment_weights": rng.normal(0, 1, (K, 6)),
            "context_weights": rng.normal(0, 1, (K, 3)), "theta": rng.normal(0, 1, 6),
            "bias": 0.5, "context_theta": rng.normal(0, 1, 3), "beta": rng.uniform(0, 0.5, K),
            "mix": 0.4, "gate": [1.0, 0.5, -0.5, 0.3, -0.2], "eps": 1e-4, "alpha0": 1.5}
  rule = jf.rules.family(params, context=names, aggregate=aggregate)
  assert rule.context == ("label_edge", "depth", "sharpness", "incidence")
  assert family_lib.terms(rule) == tuple(t for t in family_lib.TERMS if t != "spatial")
  _compare(rule, params, _frames(6))


@hypothesis.settings(max_examples=6, deadline=None)
@hypothesis.given(seed=st.integers(0, 2**16), present=st.sets(
    st.sampled_from(("table", "moments", "context", "beta", "mix")), min_size=1))
@pytest.mark.slow
def test_random_members_match_reference(seed, present):
  rng = np.random.default_rng(seed)
  params, names = {}, ()
  if "table" in present:
    params["table"] = _table(rng)
  if "moments" in present:
    params["moment_weights"] = rng.normal(0, 1.5, 6 if seed % 2 else (K, 6))
  if "context" in present:
    names = ("incidence", "radius")
    params["context_weights"] = rng.normal(0, 1.5, 2)
  if "beta" in present:
    params["beta"] = float(rng.uniform(0, 0.6))
  if "mix" in present:
    params.update(mix=float(rng.uniform(0, 1)), eps=1e-4, alpha0=1.5)
  rule = jf.rules.family(params, context=names)
  _compare(rule, params, _frames(seed % 1000, n=2, rgb=False))


def test_huge_weights_and_hard_inputs_stay_finite():
  frames = _frames(7, n=2)
  # Exponents far past the clip, on frames with holes, one-hot pixels and zero variances.
  rule = jf.rules.family({"moment_weights": np.full(6, 1e3), "table": np.full((K, 5, 4), 1e3),
                          "mix": 0.5})
  state = _fuse(rule, frames)
  out = jf.read_map(state)
  assert len(out["coords"]) > 0
  assert np.all(np.isfinite(np.asarray(state.rows["logp"])))
  np.testing.assert_allclose(out["posterior"].sum(-1), 1.0, atol=1e-5)


def test_a_member_without_d_or_gate_can_be_unfused():
  rng = np.random.default_rng(8)
  frames = _frames(8, n=3)
  rule = jf.rules.family({"table": _table(rng), "moment_weights": rng.normal(0, 0.5, 6),
                          "beta": 0.2})
  two = _fuse(rule, frames[:2])
  back = deintegration.unfuse_frame(_fuse(rule, frames), frames[2], h.CAMERA, rule)
  mask = np.asarray(two.hits) > 0
  np.testing.assert_allclose(np.asarray(back.rows["logp"])[mask],
                             np.asarray(two.rows["logp"])[mask], atol=2e-5)
  assert jf.rules.family({"mix": 0.5}).remove is None


def test_bad_parameters_are_one_clear_line():
  state = jf.init_map(capacity=256, num_classes=K, voxel_size=VOXEL,
                      rule=jf.rules.family())
  cases = [
      (lambda: jf.rules.family({"weights": [1.0]}), "unknown rule-family parameters"),
      (lambda: jf.rules.family({"table": np.ones((K, 4, 4))}).init(K, jf.rules.family(
          {"table": np.ones((K, 4, 4))}).hparams), r"table must have shape \(K, depth bins"),
      (lambda: jf.rules.family({"table": np.full((K, 5, 4), np.nan)}), "table must be finite"),
      (lambda: jf.rules.family({"table": -np.ones((K, 5, 4))}), "non-negative"),
      (lambda: jf.rules.family({"moment_weights": np.ones(5)}), r"moment_weights must have "
       r"shape \(6,\) or \(K, 6\)"),
      (lambda: jf.rules.family({"moment_weights": [np.inf] * 6}), "moment_weights must be "
       "finite"),
      (lambda: jf.rules.family({"context_weights": [1.0]}), "need context"),
      (lambda: jf.rules.family(context=("depth",)), "no context_weights or context_theta"),
      (lambda: jf.rules.family({"context_weights": [1.0, 2.0]}, context=("depth",)),
       r"context_weights must have shape \(1,\)"),
      (lambda: jf.rules.family({"mix": 1.5}), r"mix must lie in \[0, 1\]"),
      (lambda: jf.rules.family({"beta": -0.1}), r"beta must lie in \[0, 1\]"),
      (lambda: jf.rules.family({"gate": [1.0, 2.0]}), r"gate must have shape \(3,\) or \(5,\)"),
      (lambda: jf.rules.family({"depth_edges": [1.0]}), "are the table's"),
      (lambda: jf.rules.family({"table": np.ones((K, 3, 4)), "depth_edges": [2.0, 1.0]}),
       "increasing"),
  ]
  for make, message in cases:
    with pytest.raises(ValueError, match=message):
      make()
  # A table (or per-class weights) for another K: at init_map and at fuse_frame.
  other = jf.rules.family({"table": np.ones((K + 1, 5, 4))})
  with pytest.raises(ValueError, match=rf"\({K}, 5, 4\); got \({K + 1}, 5, 4\)"):
    jf.init_map(capacity=256, num_classes=K, voxel_size=VOXEL, rule=other)
  with pytest.raises(ValueError, match="moment_weights must have shape"):
    jf.fuse_frame(state, _frames(9, n=1)[0], h.CAMERA,
                  jf.rules.family({"moment_weights": np.ones((K + 2, 6))}))
