"""Per-pixel context features (docs/equations.md §2.5) against a NumPy version and hand-computed
cases; rules that ask for none are unchanged; the learned rule with context and GLFS
(§3.9, §3.10) against the NumPy reference map."""

import importlib

import hypothesis
import hypothesis.strategies as st
import jax
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import context
from tests import context_reference
from tests import engine_helpers as h
from tests.reference import ReferenceMap

learned_lib = importlib.import_module("jaxfusion.rules.learned")
CAM = jf.Camera(fx=20.0, fy=21.0, cx=9.3, cy=6.7)
CAM_TUPLE = (20.0, 21.0, 9.3, 6.7)


def scene(rng, h_=14, w_=19, k=4):
  """Depth with a step, a tilted plane, a hole and a NaN; probabilities with a NaN pixel; an
  image with a saturated patch."""
  depth = 2 + 0.05 * rng.random((h_, w_))
  depth[3:6, 4:9] += 1.0
  vv, uu = np.mgrid[0:h_, 0:w_]
  depth[h_ // 2:, w_ // 2:] = (1.5 + 0.05 * uu + 0.02 * vv)[h_ // 2:, w_ // 2:]
  depth[h_ - 3, 2] = 0.0
  depth[0, w_ // 3] = np.nan
  probs = rng.random((h_, w_, k))
  probs[2, 2] = np.nan
  rgb = rng.integers(0, 256, (h_, w_, 3), dtype=np.uint8)
  rgb[5:8, 5:8] = 255
  return depth.astype(np.float32), probs.astype(np.float32), rgb


def ours(depth, probs, names=context.FEATURES, rgb=None, cam=CAM):
  return np.asarray(context.pixel_context_jit(depth, probs, cam, tuple(names), rgb))


def test_every_feature_matches_numpy():
  depth, probs, rgb = scene(np.random.default_rng(0))
  got = ours(depth, probs, rgb=rgb)
  want = context_reference.context(depth, probs, CAM_TUPLE, context.FEATURES, rgb)
  assert np.all(np.isfinite(got))
  for f, name in enumerate(context.FEATURES):
    np.testing.assert_allclose(got[..., f], want[..., f], atol=2e-6, rtol=1e-5, err_msg=name)


@hypothesis.settings(max_examples=5, deadline=None)
@hypothesis.given(seed=st.integers(0, 2**16), h_=st.integers(3, 11), w_=st.integers(3, 11),
                  holes=st.floats(0.0, 0.4), floats=st.booleans())
def test_random_frames_match_numpy(seed, h_, w_, holes, floats):
  rng = np.random.default_rng(seed)
  depth = np.where(rng.random((h_, w_)) < holes, 0.0,
                   0.5 + 3 * rng.random((h_, w_)) ** 4).astype(np.float32)
  probs = rng.dirichlet(np.ones(3), (h_, w_)).astype(np.float32)
  rgb = (rng.random((h_, w_, 3)).astype(np.float32) if floats
         else rng.integers(0, 256, (h_, w_, 3), dtype=np.uint8))
  cam = jf.Camera(fx=9.0, fy=8.0, cx=(w_ - 1) / 2, cy=(h_ - 1) / 3)
  got = ours(depth, probs, rgb=rgb, cam=cam)
  want = context_reference.context(depth, probs, (9.0, 8.0, (w_ - 1) / 2, (h_ - 1) / 3),
                                   context.FEATURES, rgb)
  np.testing.assert_allclose(got, want, atol=3e-6, rtol=1e-5)


def test_hand_computed_cases():
  # A fronto-parallel wall seen head-on at the principal point: cos θ = 1 there, and no edges.
  wall = np.full((9, 9), 2.0, np.float32)
  probs = np.tile(np.array([0.7, 0.3], np.float32), (9, 9, 1))
  cam = jf.Camera(fx=10.0, fy=10.0, cx=4.0, cy=4.0)
  f = ours(wall, probs, ("incidence", "depth_edge", "label_edge", "radius"), cam=cam)
  assert f[4, 4, 0] == pytest.approx(1.0, abs=1e-6)
  # Off axis, a wall's cos θ is the ray's z share: 1/sqrt(1 + r²), r = |(u−cx)/fx|.
  assert f[4, 8, 0] == pytest.approx(1 / np.sqrt(1 + 0.4**2), abs=1e-5)
  assert np.all(f[..., 1] == context.MAX_EDGE_DISTANCE)
  assert np.all(f[..., 2] == context.MAX_EDGE_DISTANCE)
  assert f[4, 4, 3] == 0.0 and f[0, 0, 3] == pytest.approx(1.0) and f[8, 8, 3] == 1.0
  # A depth step between columns 4 and 5 (more than 5 %): distance |u − 4.5| − ½ to it.
  step = wall.copy()
  step[:, 5:] = 3.0
  probs2 = probs.copy()
  probs2[:, 7:] = [0.2, 0.8]                        # a label boundary between columns 6 and 7
  f = ours(step, probs2, ("depth_edge", "label_edge"), cam=cam)
  np.testing.assert_array_equal(f[0, :, 0], [4, 3, 2, 1, 0, 0, 1, 2, 3])
  np.testing.assert_array_equal(f[0, :, 1], [6, 5, 4, 3, 2, 1, 0, 0, 1])
  # 4 % is no discontinuity.
  f = ours(np.where(np.arange(9) >= 5, 2.08, 2.0).astype(np.float32)[None].repeat(9, 0),
           probs, ("depth_edge",), cam=cam)
  assert np.all(f == context.MAX_EDGE_DISTANCE)
  # A flat grey image has no Laplacian energy, its luminance, and nothing clipped; a white one
  # is all clipped.
  grey = np.full((9, 9, 3), 128, np.uint8)
  f = ours(wall, probs, ("sharpness", "luminance", "clipped"), rgb=grey, cam=cam)
  np.testing.assert_allclose(f[..., 0], 0.0, atol=1e-6)
  np.testing.assert_allclose(f[..., 1], 128 / 255, atol=1e-6)
  assert np.all(f[..., 2] == 0.0)
  f = ours(wall, probs, ("clipped",), rgb=np.full((9, 9, 3), 255, np.uint8), cam=cam)
  assert np.all(f == 1.0)


def test_names_are_checked():
  depth, probs, rgb = scene(np.random.default_rng(1))
  with pytest.raises(ValueError, match="unknown context features"):
    context.pixel_context(depth, probs, CAM, ("depth", "normal"))
  with pytest.raises(ValueError, match="must not repeat"):
    context.pixel_context(depth, probs, CAM, ("depth", "depth"))
  with pytest.raises(ValueError, match="colour image"):
    context.pixel_context(depth, probs, CAM, ("luminance",))
  # Order is the caller's.
  a = ours(depth, probs, ("radius", "depth"))
  b = ours(depth, probs, ("depth", "radius"))
  np.testing.assert_array_equal(a, b[..., ::-1])


def _fuse(rule, frames, capacity=1024):
  state = jf.init_map(capacity=capacity, num_classes=h.NUM_CLASSES, voxel_size=0.25, rule=rule)
  for f in frames:
    state = jf.fuse_frame(state, f, h.CAMERA, rule)
  return state


def _frames(seed, n=3, rgb=True):
  rng = np.random.default_rng(seed)
  out = []
  for _ in range(n):
    f = h.random_frame(rng, voxel_size=0.25)
    image = rng.integers(0, 256, np.shape(f.depth) + (3,), dtype=np.uint8) if rgb else None
    out.append(f._replace(rgb=image))
  return out


@pytest.mark.parametrize("name", ["bayes", "robust_dr", "sum_labels"])
def test_rules_without_context_ignore_the_image_and_compute_none(name):
  rule = jf.rules.by_name(name)
  with_rgb = _frames(2)
  without = [f._replace(rgb=None) for f in with_rgb]
  a, b = _fuse(rule, with_rgb), _fuse(rule, without)
  for x, y in zip(jax.tree.leaves(a.rows), jax.tree.leaves(b.rows)):
    np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
  # The traced program reads no context: no image windows (`reduce_window`), and no loop of a
  # depth edge's dilations beyond what the learned rule's own program has.
  def jaxpr(r):
    state = jf.init_map(capacity=256, num_classes=h.NUM_CLASSES, voxel_size=0.25, rule=r)
    return str(jax.make_jaxpr(jf.fusion.fuse_frame_unchecked)(state, with_rgb[0], h.CAMERA, r))

  plain = jaxpr(rule)
  assert "reduce_window" not in plain
  assert "reduce_window" in jaxpr(jf.rules.learned(context=("sharpness",)))
  loops = lambda text: text.count("while[") + text.count("scan[")
  learned_plain = loops(jaxpr(jf.rules.learned()))
  assert loops(jaxpr(jf.rules.learned(context=("depth_edge",)))) == learned_plain + 1
  assert loops(plain) <= learned_plain


def _reference_context(frame, names):
  c = h.CAMERA
  return context_reference.context(np.asarray(frame.depth), np.asarray(frame.probs),
                                   (c.fx, c.fy, c.cx, c.cy), names, frame.rgb)


def _compare(rule, reference, frames, names):
  state = _fuse(rule, frames)
  c = h.CAMERA
  for f in frames:
    reference.fuse(np.asarray(f.depth), np.asarray(f.T_world_cam), np.asarray(f.probs),
                   None if f.var is None else np.asarray(f.var), c.fx, c.fy, c.cx, c.cy,
                   ctx=_reference_context(f, names))
  ours_map, ref = jf.read_map(state), reference.read()
  order = np.lexsort(np.asarray(ours_map["coords"]).T[::-1])
  np.testing.assert_array_equal(np.asarray(ours_map["coords"])[order], ref["coords"])
  np.testing.assert_allclose(np.asarray(ours_map["posterior"])[order], ref["posterior"],
                             atol=2e-5, rtol=1e-4)


@pytest.mark.parametrize("seed", [0, 1])
def test_learned_with_context_matches_reference(seed):
  rng = np.random.default_rng(seed)
  k, names = h.NUM_CLASSES, context.FEATURES
  params = {"theta": rng.normal(0, 1, (k, 6)), "bias": rng.normal(0.5, 1, k),
            "context_theta": rng.normal(0, 1, (k, len(names))), "mix": 0.6,
            "gate": [1.0, rng.normal(), rng.normal(), rng.normal(), rng.normal()],
            "beta": rng.uniform(0, 0.5, k), "eps": 1e-4, "alpha0": 1.5}
  rule = jf.rules.learned(params, context=names)
  ref = ReferenceMap("learned", k, 0.25, beta=params["beta"], eps=1e-4, alpha0=1.5,
                     learned=params, context=names)
  _compare(rule, ref, _frames(10 + seed), names)


def test_learned_shared_weights_with_some_context_match_reference():
  rng = np.random.default_rng(5)
  names = ("label_edge", "depth")
  params = {"theta": rng.normal(0, 1, 6), "bias": 0.3, "context_theta": [0.8, -1.2],
            "mix": 0.3, "gate": [2.0, -1.0, 0.5], "beta": 0.2, "eps": 1e-4, "alpha0": 1.5}
  rule = jf.rules.learned(params, context=names)
  ref = ReferenceMap("learned", h.NUM_CLASSES, 0.25, beta=0.2, eps=1e-4, alpha0=1.5,
                     learned=params, context=names)
  _compare(rule, ref, _frames(20, rgb=False), names)


def test_learned_with_context_still_contains_the_paper_rules():
  frames = _frames(3)
  for name in ("bayes", "robust_dr"):
    paper = _fuse(jf.rules.by_name(name), frames)
    k = h.NUM_CLASSES
    params = {**learned_lib.special_case(name), "theta": np.zeros((k, 6)),
              "bias": np.full(k, learned_lib.ON), "context_theta": np.zeros((k, 8)),
              "gate": [learned_lib.ON, 0, 0, 0, 0]}
    ours_map = _fuse(jf.rules.learned(params, context=context.FEATURES), frames)
    np.testing.assert_allclose(np.asarray(ours_map.rows["logp"]), np.asarray(paper.rows["logp"]),
                               atol=1e-6, rtol=1e-6)


def test_glfs_matches_reference_and_ones_are_bayes():
  rng = np.random.default_rng(7)
  frames = _frames(4, rgb=False)
  k = h.NUM_CLASSES
  table = rng.uniform(0, 2, (k, 5, 4))
  rule = jf.rules.glfs(table)
  ref = ReferenceMap("glfs", k, 0.25, glfs=(table, jf.rules.glfs_lib.DEPTH_EDGES,
                                            jf.rules.glfs_lib.ANGLE_EDGES))
  frames = [f._replace(var=None) for f in frames]
  _compare(rule, ref, frames, ("depth", "incidence"))
  ones = _fuse(jf.rules.glfs(num_classes=k), frames)
  bayes = _fuse(jf.rules.bayes(), frames)
  np.testing.assert_array_equal(np.asarray(ones.rows["logp"]), np.asarray(bayes.rows["logp"]))


def test_inputs_are_checked():
  frames = _frames(6, n=1)
  rule = jf.rules.learned(context=("luminance",))
  state = jf.init_map(capacity=256, num_classes=h.NUM_CLASSES, voxel_size=0.25, rule=rule)
  with pytest.raises(ValueError, match=r"reads image context features \['luminance'\]"):
    jf.fuse_frame(state, frames[0]._replace(rgb=None), h.CAMERA, rule)
  with pytest.raises(ValueError, match="rgb must have shape"):
    jf.fuse_frame(state, frames[0]._replace(rgb=frames[0].rgb[:, :-1]), h.CAMERA, rule)
  with pytest.raises(TypeError, match="rgb must be uint8 or float"):
    jf.fuse_frame(state, frames[0]._replace(rgb=frames[0].rgb.astype(np.int32)), h.CAMERA,
                  rule)
  with pytest.raises(ValueError, match="unknown context features"):
    jf.rules.learned(context=("normals",))
  with pytest.raises(ValueError, match="context_theta needs context"):
    jf.rules.learned({"context_theta": [1.0]})
  with pytest.raises(ValueError, match="context_theta must have shape"):
    jf.rules.learned({"context_theta": [1.0, 2.0]}, context=("depth",))
  with pytest.raises(ValueError, match="gate"):
    jf.rules.learned({"gate": [1.0, 2.0, 3.0, 4.0]})
  with pytest.raises(ValueError, match="non-negative"):
    jf.rules.glfs(-np.ones((3, 5, 4)))
  with pytest.raises(ValueError, match="GLFS table must have shape"):
    jf.rules.glfs(np.ones((3, 4, 4)))
  with pytest.raises(ValueError, match="increasing"):
    jf.rules.glfs(num_classes=3, depth_edges=(2.0, 1.0))


@pytest.mark.slow
def test_gradient_reaches_the_context_weights():
  frames = _frames(8, n=2)
  names = ("depth", "incidence", "luminance")
  k = h.NUM_CLASSES

  def loss(ct):
    rule = jf.rules.learned({"context_theta": ct, "bias": 0.0, "mix": 0.5}, context=names)
    state = jf.init_map(capacity=512, num_classes=k, voxel_size=0.25, rule=rule)
    for f in frames:
      state = jf.fuse_frame(state, f, h.CAMERA, rule)
    occupied = state.hits > 0
    return -jax.numpy.sum(jax.nn.log_softmax(state.rows["logp"])[:, 0] * occupied)

  ct = jax.numpy.array([0.3, -0.2, 0.1])
  g = np.asarray(jax.grad(loss)(ct))
  assert np.all(np.isfinite(g)) and np.any(g != 0)
  step = 1e-2
  for i in range(3):
    e = np.zeros(3, np.float32)
    e[i] = step
    fd = (float(loss(ct + e)) - float(loss(ct - e))) / (2 * step)
    assert g[i] == pytest.approx(fd, rel=0.05, abs=1e-2)
