"""Hand-computed small cases, the paper's outlier claim, and the engine's handling of bad input,
full maps and far-away keys."""

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import jaxfusion as jf
from jaxfusion import validation
from tests import engine_helpers as h

# A 2×2 image at 0.9 m depth: its points lie within ±0.05 m of (0.5, 0.5, 0.9), one 1 m voxel.
CAM = jf.Camera(10.0, 10.0, 0.5, 0.5)
EYE = np.eye(4, dtype=np.float32)
POSE = EYE.copy()
POSE[:2, 3] = 0.5


def one_voxel_frame(p, var=None, pixels=1):
  """A frame whose `pixels` valid pixels (of 2×2) all see class probabilities `p` in voxel
  (0, 0, 0) — 1 m voxels, depth 0.9 m, centred camera."""
  p = np.asarray(p, np.float32)
  depth = np.zeros((2, 2), np.float32)
  depth.reshape(-1)[:pixels] = 0.9
  probs = np.broadcast_to(p, (2, 2, len(p))).copy()
  v = None if var is None else np.broadcast_to(np.asarray(var, np.float32), probs.shape).copy()
  return jf.Frame(depth, POSE, probs, v)


def fuse_all(rule, frames, num_classes=3, voxel_size=1.0):
  state = jf.init_map(capacity=16, num_classes=num_classes, voxel_size=voxel_size, rule=rule)
  for f in frames:
    state = jf.fuse_frame(state, f, CAM, rule)
  return jf.read_map(state)


def test_bayes_by_hand():
  p = [0.7, 0.2, 0.1]
  out = fuse_all(jf.rules.bayes(), [one_voxel_frame(p)])
  np.testing.assert_allclose(out["posterior"][0], p, rtol=1e-6)
  out = fuse_all(jf.rules.bayes(), [one_voxel_frame(p), one_voxel_frame(p)])
  np.testing.assert_allclose(out["posterior"][0], np.square(p) / np.sum(np.square(p)), rtol=1e-6)
  # Three pixels in one voxel in one frame: the paper's Σ_j multiplies all three …
  out = fuse_all(jf.rules.bayes(), [one_voxel_frame(p, pixels=3)])
  np.testing.assert_allclose(out["posterior"][0], np.power(p, 3) / np.sum(np.power(p, 3)),
                             rtol=1e-5)
  assert out["hits"][0] == 3
  # … while aggregate="mean" counts them as one observation.
  out = fuse_all(jf.rules.bayes(aggregate="mean"), [one_voxel_frame(p, pixels=3)])
  np.testing.assert_allclose(out["posterior"][0], p, rtol=1e-5)


def test_sum_probs_and_sum_labels_by_hand():
  frames = [one_voxel_frame([0.5, 0.3, 0.2], pixels=2), one_voxel_frame([0.1, 0.45, 0.45])]
  out = fuse_all(jf.rules.sum_probs(), frames)
  np.testing.assert_allclose(out["posterior"][0], np.array([1.1, 1.05, 0.85]) / 3.0, rtol=1e-6)
  assert out["labels"][0] == 0
  out = fuse_all(jf.rules.sum_labels(), frames)   # votes: class 0 twice, class 1 once
  np.testing.assert_allclose(out["posterior"][0], [2 / 3, 1 / 3, 0.0], rtol=1e-6)
  np.testing.assert_allclose(out["entropy"][0], -(2 / 3 * math.log(2 / 3) + 1 / 3 *
                                                   math.log(1 / 3)), rtol=1e-5)


def test_robust_r_by_hand():
  p = np.array([0.9, 0.1, 0.0])
  out = fuse_all(jf.rules.robust(beta=0.3, dirichlet=False), [one_voxel_frame(p)])
  np.testing.assert_allclose(out["posterior"][0], 0.7 * p + 0.1, rtol=1e-6)


def test_dirichlet_by_hand():
  # Frame 1: var 0.01 → α = −log(0.01) = 4.605; ᾱ_0 = 0, so ᾱ_1 = α and the weight is 1.
  # Frame 2: var 0.1 → α = 2.303 < ᾱ_1: log P_2 = log P_1 + (α_2/ᾱ_1) log p_2, normalised.
  p1, p2 = np.array([0.6, 0.3, 0.1]), np.array([0.1, 0.8, 0.1])
  rule = jf.rules.robust(regularize=False, alpha0=0.0, eps=1e-12)
  out = fuse_all(rule, [one_voxel_frame(p1, 0.01), one_voxel_frame(p2, 0.1)])
  logp = np.log(p1) + (math.log(0.1) / math.log(0.01)) * np.log(p2)
  want = np.exp(logp) / np.exp(logp).sum()
  np.testing.assert_allclose(out["posterior"][0], want, rtol=1e-5)
  np.testing.assert_allclose(out["confidence"][0], -math.log(0.01), rtol=1e-6)
  # With the default α₀ = −log(1e-3), a first observation with variance 0.01 is discounted.
  out = fuse_all(jf.rules.robust(regularize=False), [one_voxel_frame(p1, 0.01)])
  w = math.log(0.01) / math.log(1e-3)
  want = np.exp(w * np.log(p1)) / np.exp(w * np.log(p1)).sum()
  np.testing.assert_allclose(out["posterior"][0], want, rtol=1e-5)


def outlier_sequence(n_agree=5):
  agree = [one_voxel_frame([0.6, 0.2, 0.2], var=0.001) for _ in range(n_agree)]
  outlier = one_voxel_frame([0.001, 0.998, 0.001], var=0.1)   # confident, wrong, unfamiliar
  return agree, outlier


def test_paper_claim_one_outlier_flips_bayes_but_not_robust():
  agree, outlier = outlier_sequence()
  assert fuse_all(jf.rules.bayes(), agree)["labels"][0] == 0
  assert fuse_all(jf.rules.bayes(), agree + [outlier])["labels"][0] == 1   # flipped
  for rule in (jf.rules.robust(dirichlet=False), jf.rules.robust(regularize=False),
               jf.rules.robust()):
    assert fuse_all(rule, agree + [outlier])["labels"][0] == 0, rule.name


@settings(max_examples=25, deadline=None)
@given(n_agree=st.integers(5, 12), p_true=st.floats(0.5, 0.95),
       wrong=st.floats(0.9, 1.0), var_agree=st.floats(0.0, 0.01), var_out=st.floats(0.05, 0.25))
def test_outlier_property_robust_dr(n_agree, p_true, wrong, var_agree, var_out):
  """One confident wrong frame with high epistemic variance cannot flip a voxel that D+R has
  seen a few times agreeing with low variance."""
  rest = (1 - p_true) / 2
  agree = [one_voxel_frame([p_true, rest, rest], var=var_agree)] * n_agree
  outlier = one_voxel_frame([(1 - wrong) / 2, wrong, (1 - wrong) / 2], var=var_out)
  out = fuse_all(jf.rules.robust(), agree + [outlier])
  assert out["labels"][0] == 0
  assert np.all(np.isfinite(out["posterior"]))


@pytest.mark.slow
@settings(max_examples=6, deadline=None)
@given(seed=st.integers(0, 2**16), name=st.sampled_from(["sum_probs", "sum_labels", "bayes",
                                                        "robust_r"]))
def test_commutative_rules_do_not_depend_on_frame_order(seed, name):
  rng = np.random.default_rng(seed)
  frames = [h.random_frame(rng) for _ in range(3)]
  rule = jf.rules.by_name(name)
  outs = []
  for order in ([0, 1, 2], [2, 0, 1]):
    state = jf.init_map(capacity=512, num_classes=h.NUM_CLASSES, voxel_size=0.25, rule=rule)
    for i in order:
      state = jf.fuse_frame(state, frames[i], h.CAMERA, rule)
    outs.append(jf.read_map(state))
  np.testing.assert_array_equal(outs[0]["coords"], outs[1]["coords"])
  np.testing.assert_allclose(outs[0]["posterior"], outs[1]["posterior"], atol=1e-5)


def test_far_keys_do_not_wrap_around():
  # A camera 999 m out along each axis; keys must be floor(p / 0.1) exactly, with no wrap.
  T = EYE.copy()
  T[:3, 3] = [999.0, -999.0, -999.5]
  depth = np.full((2, 2), 0.95, np.float32)
  frame = jf.Frame(depth, T, np.full((2, 2, 3), 1 / 3, np.float32))
  rule = jf.rules.bayes()
  state = jf.init_map(capacity=16, num_classes=3, voxel_size=0.1, rule=rule)
  out = jf.read_map(jf.fuse_frame(state, frame, jf.Camera(10.0, 10.0, 0.5, 0.5), rule))
  u = np.array([0, 1, 0, 1]) - 0.5
  v = np.array([0, 0, 1, 1]) - 0.5
  pts = np.stack([0.95 * u / 10, 0.95 * v / 10, np.full(4, 0.95)], -1) + T[:3, 3]
  want = np.unique(np.floor(pts / 0.1).astype(np.int64), axis=0)
  np.testing.assert_array_equal(out["coords"], want)
  assert np.all(np.abs(out["coords"]) > 9000)


@pytest.mark.parametrize("free_space", [False, True])
def test_full_map_drops_counts_and_never_corrupts(free_space):
  rng = np.random.default_rng(0)
  rule = jf.rules.bayes()
  state = jf.init_map(capacity=16, num_classes=h.NUM_CLASSES, voxel_size=0.05, rule=rule,
                      free_space=free_space)
  frame = h.random_frame(rng, voxel_size=0.05)
  state = jf.fuse_frame(state, frame, h.CAMERA, rule)
  with pytest.warns(jf.MapFullWarning):
    first = jf.read_map(state)
  assert len(first["coords"]) == 16
  with pytest.warns(jf.MapFullWarning):
    stats = jf.map_stats(state)
  n_valid_voxels = len(np.unique(
      np.floor(_world_points(frame) / 0.05).astype(np.int64), axis=0))
  assert stats["occupied"] == 16 and stats["dropped"] == n_valid_voxels - 16
  # A second frame of entirely new voxels: nothing fits, the stored voxels are untouched.
  far = h.random_frame(rng, voxel_size=0.05, T=_translation(100.0))
  state = jf.fuse_frame(state, far, h.CAMERA, rule)
  with pytest.warns(jf.MapFullWarning):
    second = jf.read_map(state)
  np.testing.assert_array_equal(second["coords"], first["coords"])
  np.testing.assert_array_equal(second["posterior"], first["posterior"])


def _translation(x):
  T = np.eye(4, dtype=np.float32)
  T[0, 3] = x
  return T


def _world_points(frame):
  from tests.reference import pixel_points
  return np.array([p for _, p in pixel_points(frame.depth, frame.T_world_cam, *h.CAMERA)])


def test_bad_pixels_never_reach_the_map():
  depth = np.array([[1.0, np.nan], [np.inf, -2.0]], np.float32)
  probs = np.full((2, 2, 3), 1 / 3, np.float32)
  probs[0, 0] = [1.0, 0.0, 0.0]   # hard zeros
  probs[1, 0] = [np.nan, 0.5, 0.5]
  var = np.zeros((2, 2, 3), np.float32)   # zero variance
  for name in h.PAPER_RULES:
    rule = jf.rules.by_name(name)
    out = fuse_all(rule, [jf.Frame(depth, POSE, probs, var)] * 3)
    assert len(out["coords"]) == 1 and out["hits"][0] == 3
    assert np.all(np.isfinite(out["posterior"])) and np.all(np.isfinite(out["entropy"]))
    assert out["labels"][0] == 0


# --- bad input: clear ValueError / TypeError ---------------------------------------------------
def good():
  rule = jf.rules.robust()
  state = jf.init_map(capacity=16, num_classes=3, voxel_size=1.0, rule=rule)
  return state, one_voxel_frame([0.5, 0.3, 0.2], var=0.01), rule


@pytest.mark.parametrize("change,error,match", [
    (lambda f: f._replace(depth=f.depth[0]), ValueError, "depth must have shape"),
    (lambda f: f._replace(depth=(f.depth * 1000).astype(np.uint16)), TypeError, "mm / 1000"),
    (lambda f: f._replace(probs=f.probs[..., :2], var=f.var[..., :2]), ValueError,
     "K mismatch"),
    (lambda f: f._replace(probs=f.probs[:1]), ValueError, "same pixels"),
    (lambda f: f._replace(T_world_cam=np.eye(3, dtype=np.float32)), ValueError, "4, 4"),
    (lambda f: f._replace(T_world_cam=np.full((4, 4), np.nan, np.float32)), ValueError,
     "finite"),
    (lambda f: f._replace(T_world_cam=np.diag([2.0, 1, 1, 1]).astype(np.float32)), ValueError,
     "not rigid"),
    (lambda f: f._replace(T_world_cam=np.diag([-1.0, 1, 1, 1]).astype(np.float32)),
     ValueError, "determinant"),
    (lambda f: f._replace(probs=f.probs - 1.0), ValueError, "non-negative"),
    (lambda f: f._replace(var=None), ValueError, "var="),
    (lambda f: f._replace(var=f.var[..., :1]), ValueError, "shape of probs"),
])
def test_bad_frames_are_refused_clearly(change, error, match):
  state, frame, rule = good()
  with pytest.raises(error, match=match):
    jf.fuse_frame(state, change(frame), CAM, rule)


def test_logits_and_negative_variances_are_refused_from_host_and_device_arrays():
  rng = np.random.default_rng(0)
  rule = jf.rules.robust()
  probs = rng.dirichlet(np.ones(3), (48, 64)).astype(np.float32)
  depth = np.ones((48, 64), np.float32)
  var = np.full_like(probs, 0.01)
  state = jf.init_map(capacity=2**12, num_classes=3, voxel_size=0.5, rule=rule)
  for to in (np.asarray, jnp.asarray):
    with pytest.raises(ValueError, match="log-probabilities"):
      jf.fuse_frame(state, jf.Frame(to(depth), POSE, to(np.log(probs)), to(var)), CAM, rule)
    with pytest.raises(ValueError, match="negative variances"):
      jf.fuse_frame(state, jf.Frame(to(depth), POSE, to(probs), to(var - 0.02)), CAM, rule)


def test_sampled_sign_check_of_fuse_frame_and_full_check_of_fuse_sequence():
  # 64×96 pixels: ceil(6144 / SAMPLED_PIXELS) = 2, fuse_frame reads every other pixel from 0.
  assert validation.SAMPLED_PIXELS == 4096
  rule = jf.rules.bayes()
  probs = np.full((64, 96, 3), 1 / 3, np.float32)
  depth = np.ones((64, 96), np.float32)
  unsampled = probs.copy()
  unsampled[0, 1] = [-0.25, 0.625, 0.625]          # pixel 1: not in the sample
  sampled = probs.copy()
  sampled[0, 2] = [-0.25, 0.625, 0.625]            # pixel 2: in the sample
  fresh = lambda: jf.init_map(capacity=2**12, num_classes=3, voxel_size=0.5, rule=rule)
  with pytest.raises(ValueError, match="non-negative"):
    jf.fuse_frame(fresh(), jf.Frame(depth, POSE, sampled), CAM, rule)
  # A missed negative entry is read as max(p, 0), as the engine always does.
  clamped = unsampled.copy()
  clamped[0, 1, 0] = 0.0
  got = jf.read_map(jf.fuse_frame(fresh(), jf.Frame(depth, POSE, unsampled), CAM, rule))
  want = jf.read_map(jf.fuse_frame(fresh(), jf.Frame(depth, POSE, clamped), CAM, rule))
  np.testing.assert_array_equal(got["posterior"], want["posterior"])
  # Sequences check every value, once per call.
  stack = jf.Frame(depth[None], POSE[None], unsampled[None])
  with pytest.raises(ValueError, match="non-negative"):
    jf.fuse_sequence(fresh(), stack, CAM, rule)


def test_bad_camera_rule_and_map_arguments():
  state, frame, rule = good()
  with pytest.raises(ValueError, match="focal length"):
    jf.fuse_frame(state, frame, jf.Camera(0.0, 1.0, 0.5, 0.5), rule)
  with pytest.raises(TypeError, match="Camera"):
    jf.fuse_frame(state, frame, (1.0, 1.0, 0.5, 0.5), rule)
  with pytest.raises(ValueError, match="made for rule 'robust_dr'"):
    jf.fuse_frame(state, frame, CAM, jf.rules.bayes())
  with pytest.raises(ValueError, match="voxel_size"):
    jf.init_map(capacity=16, num_classes=3, voxel_size=0.0, rule=rule)
  with pytest.raises(ValueError, match="num_classes"):
    jf.init_map(capacity=16, num_classes=1, rule=rule)
  with pytest.warns(UserWarning, match="rounded up to 32"):
    assert jf.init_map(capacity=20, num_classes=3, rule=rule).capacity == 32
  with pytest.raises(ValueError, match="beta"):
    jf.rules.robust(beta=1.5)
  with pytest.raises(ValueError, match="eps"):
    jf.rules.robust(eps=0.0)
  with pytest.raises(ValueError, match="unknown rule"):
    jf.rules.by_name("kalman")
  with pytest.raises(ValueError, match="aggregate"):
    jf.rules.bayes(aggregate="median")


@pytest.mark.slow
@pytest.mark.parametrize("free_space", [False, True])
def test_fuse_sequence_equals_a_loop_of_fuse_frame(free_space):
  rng = np.random.default_rng(11)
  frames = [h.random_frame(rng) for _ in range(3)]
  if free_space:   # frame 2 looks from frame 0's pose at a wall behind it: voxels are freed
    seen = np.isfinite(frames[0].depth) & (frames[0].depth > 0)
    wall = np.where(np.isfinite(frames[2].depth) & (frames[2].depth > 0),
                    frames[0].depth[seen].max() + 1.0, frames[2].depth).astype(np.float32)
    frames[2] = frames[2]._replace(depth=wall, T_world_cam=frames[0].T_world_cam)
    free_space = jf.FreeSpaceConfig(prob_miss=0.2)      # one miss frees a voxel hit once
  rule = jf.rules.robust()
  make = lambda: jf.init_map(capacity=512, num_classes=h.NUM_CLASSES, voxel_size=0.25,
                             rule=rule, free_space=free_space)
  state = make()
  for f in frames:
    state = jf.fuse_frame(state, f, h.CAMERA, rule)
  stacked = jax.tree.map(lambda *x: np.stack(x), *frames)
  seq = jf.fuse_sequence(make(), stacked, h.CAMERA, rule)
  a, b = jf.read_map(state), jf.read_map(seq)
  np.testing.assert_array_equal(a["coords"], b["coords"])
  np.testing.assert_allclose(a["posterior"], b["posterior"], atol=1e-6)
  np.testing.assert_array_equal(a["hits"], b["hits"])
  assert (jf.map_stats(seq).get("free", 0) > 0) == bool(free_space)


@pytest.mark.parametrize("bad", ["nan", "none", "inf"])
@pytest.mark.parametrize("on_device", [False, True])
def test_a_nan_does_not_hide_negative_probabilities_or_variances(on_device, bad):
  # Found by bench/fuzz.py: the sign checks took a plain minimum, which a NaN anywhere turns
  # into NaN (and NaN < 0 is False), so negative values passed. On device the check takes a
  # plain minimum unless the array's sum says it holds a NaN (or both infinities): every case
  # must still see the negative entry.
  rule = jf.rules.robust()
  camera = jf.Camera(8.0, 8.0, 3.5, 2.5)
  put = jax.device_put if on_device else (lambda x: x)
  for field in ("probs", "var"):
    probs = np.full((6, 8, 3), 1 / 3, np.float32)
    var = np.full((6, 8, 3), 0.01, np.float32)
    target = probs if field == "probs" else var
    target[0, 0, 0] = -0.5
    if bad == "nan":
      target[5, 7, 1] = np.nan
    elif bad == "inf":
      target[5, 7, 1], target[4, 2, 2] = np.inf, -np.inf
    frame = jf.Frame(np.full((6, 8), 2.0, np.float32), np.eye(4, dtype=np.float32),
                     put(probs), put(var))
    with pytest.raises(ValueError, match="negative"):
      jf.fuse_frame(jf.init_map(capacity=256, num_classes=3, rule=rule), frame, camera, rule)
    with pytest.raises(ValueError, match="negative"):
      jf.fuse_sequence(jf.init_map(capacity=256, num_classes=3, rule=rule),
                       jax.tree.map(lambda x: x[None], frame), camera, rule)
