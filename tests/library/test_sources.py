"""Probability sources: every adapter yields (probs, var) that `fuse_frame` accepts end to end."""

import hypothesis
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import strategies as st

import jaxfusion
from jaxfusion import sources
from models import net, sampling

H, W, K = 16, 16, 7
M = 4
CAMERA = jaxfusion.Camera(12.0, 12.0, 7.5, 7.5)


def init(seed):
  """Tiny-net weights from an RBG key: any weights do here, and XLA on CPU compiles the
  initialiser's threefry ops several times slower than rbg's."""
  return net.init(net.tiny_config(K), key=jax.random.key(seed, impl="rbg"))


@pytest.fixture(scope="module")
def tiny():
  return init(0)


@pytest.fixture(scope="module")
def image():
  return np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)


def _fuse(prediction, rule):
  """Fuses one frame at 1 m in front of the camera; returns the read-out map."""
  state = jaxfusion.init_map(capacity=1024, num_classes=K, voxel_size=0.1, rule=rule)
  depth = np.full((H, W), 1.0, np.float32)
  frame = jaxfusion.Frame(depth, np.eye(4, dtype=np.float32), prediction.probs, prediction.var)
  state = jaxfusion.fuse_frame(state, frame, CAMERA, rule)
  out = jaxfusion.read_map(state)
  assert out["coords"].shape[0] > 0
  assert np.all(np.isfinite(out["posterior"]))
  np.testing.assert_allclose(out["posterior"].sum(-1), 1.0, atol=1e-4)
  return out


def _check_prediction(pred, *, with_var):
  assert isinstance(pred, sources.Prediction)
  assert pred.probs.shape == (H, W, K) and pred.probs.dtype == jnp.float32
  np.testing.assert_allclose(np.asarray(pred.probs).sum(-1), 1.0, atol=1e-5)
  if with_var:
    assert pred.var.shape == (H, W, K) and float(pred.var.min()) >= 0.0
  else:
    assert pred.var is None


@pytest.mark.slow
def test_mc_dropout_source_feeds_robust_fusion(tiny, image):
  graphdef, params = tiny
  source = sampling.mc_dropout_source(graphdef, params, num_samples=M)
  assert isinstance(source, sources.ProbabilitySource)
  pred = source.predict(jax.random.key(1), image)
  _check_prediction(pred, with_var=True)
  assert float(pred.var.max()) > 0.0
  # Equal to the models' own jitted sampler followed by mc_moments (same keys, same masks).
  mean, var = jaxfusion.mc_moments(
      sampling.mc_samples(graphdef, params, jax.random.key(1), image, num_samples=M))
  np.testing.assert_allclose(np.asarray(pred.probs), np.asarray(mean), atol=1e-5)
  np.testing.assert_allclose(np.asarray(pred.var), np.asarray(var), atol=1e-5)
  _fuse(pred, jaxfusion.rules.robust(beta=0.3))


def test_deterministic_source_feeds_bayes_fusion_and_has_no_variance(tiny, image):
  graphdef, params = tiny
  source = sampling.deterministic_source(graphdef, params)
  pred = source.predict(None, image)
  _check_prediction(pred, with_var=False)
  np.testing.assert_allclose(np.asarray(pred.probs),
                             np.asarray(sampling.deterministic_probs(graphdef, params, image)),
                             atol=1e-5)
  _fuse(pred, jaxfusion.rules.bayes())


def test_stochastic_source_needs_a_key(tiny, image):
  graphdef, params = tiny
  with pytest.raises(ValueError, match="PRNG key"):
    sampling.mc_dropout_source(graphdef, params, num_samples=M).predict(None, image)


def test_ensemble_source_mean_and_variance_across_members(tiny, image):
  graphdef, params = tiny
  members = [params] + [init(s)[1] for s in (1, 2)]
  source = sampling.ensemble_source(graphdef, members)
  pred = source.predict(jax.random.key(0), image)
  _check_prediction(pred, with_var=True)
  each = np.stack([np.asarray(sampling.deterministic_probs(graphdef, p, image)) for p in members])
  np.testing.assert_allclose(np.asarray(pred.probs), each.mean(0), atol=1e-5)
  np.testing.assert_allclose(np.asarray(pred.var), each.var(0), atol=1e-5)
  _fuse(pred, jaxfusion.rules.robust(beta=0.3))


def test_ensemble_source_rejects_mismatched_members(tiny):
  graphdef, params = tiny
  # Shapes are all that is compared, so abstract parameters (no allocation) suffice.
  other = net.abstract_params(net.SegNetConfig(
      num_classes=K, stem_width=8, widths=(16,), strides=(2,), dilations=(1,), aspp_width=8,
      aspp_rates=(2,), norm_groups=4))[1]
  with pytest.raises(ValueError, match="member 1"):
    sources.ensemble_source(sampling.deterministic_apply_fn(graphdef), [params, other])
  with pytest.raises(ValueError, match="at least one"):
    sources.ensemble_source(sampling.deterministic_apply_fn(graphdef), [])


def test_segment_fn_source_with_a_plain_function():
  """Any segment_fn works — here a hand-written 'network' with no Flax at all."""
  def segment_fn(temperature, key, image):
    logits = jnp.stack([image[..., 0], image[..., 1], 1.0 - image[..., 0]], -1)
    noise = 0.1 * jax.random.normal(key, (5,) + logits.shape)
    return jax.nn.softmax((logits[None] + noise) / temperature, axis=-1)

  image = jnp.asarray(np.random.default_rng(1).random((H, W, 3)), jnp.float32)
  source = sources.segment_fn_source(segment_fn, jnp.float32(0.5))
  pred = source.predict(jax.random.key(0), image)
  assert pred.probs.shape == (H, W, 3) and pred.var.shape == (H, W, 3)
  batch = source.predict_batch(jax.random.key(0), jnp.stack([image, image]))
  assert batch.probs.shape == (2, H, W, 3)
  bad = sources.segment_fn_source(lambda p, k, im: im, None)
  with pytest.raises(ValueError, match=r"\(M, H, W, K\)"):
    bad.predict(jax.random.key(0), image)


def test_network_source_batch_matches_single_frames(tiny, image):
  graphdef, params = tiny
  source = sampling.deterministic_source(graphdef, params)
  images = np.stack([image, image[:, ::-1]])
  batch = source.predict_batch(None, images)
  assert batch.probs.shape == (2, H, W, K) and batch.var is None
  for b in range(2):
    single = source.predict(None, images[b])
    np.testing.assert_allclose(np.asarray(batch.probs[b]), np.asarray(single.probs), atol=1e-5)


def _dirichlet(rng, shape):
  return rng.dirichlet(np.ones(K), shape).astype(np.float32)


def test_precomputed_source_reads_mean_var_and_samples(tmp_path):
  rng = np.random.default_rng(0)
  mean0 = _dirichlet(rng, (H, W))
  var0 = rng.uniform(0, 0.01, (H, W, K)).astype(np.float32)
  samples2 = _dirichlet(rng, (M, H, W))
  sources.save_prediction(tmp_path / "000000.npz", mean=mean0, var=var0)
  sources.save_prediction(tmp_path / "000001.npz", mean=mean0)
  sources.save_prediction(tmp_path / "000002.npz", samples=samples2)
  source = sources.precomputed_source(tmp_path)
  assert isinstance(source, sources.ProbabilitySource)
  assert len(source) == 3

  p0 = source.predict(None, None, index=0)
  np.testing.assert_array_equal(np.asarray(p0.probs), mean0)
  np.testing.assert_array_equal(np.asarray(p0.var), var0)
  _fuse(p0, jaxfusion.rules.robust(beta=0.3))
  p1 = source.predict(None, np.zeros((H, W, 3), np.uint8), index=1)
  assert p1.var is None
  _fuse(p1, jaxfusion.rules.bayes())
  p2 = source.predict(None, None, index=2)
  mean2, var2 = jaxfusion.mc_moments(samples2)
  np.testing.assert_allclose(np.asarray(p2.probs), np.asarray(mean2), atol=1e-5)
  np.testing.assert_allclose(np.asarray(p2.var), np.asarray(var2), atol=1e-6)
  _fuse(p2, jaxfusion.rules.robust(beta=0.3))


def test_precomputed_source_channels_first_like_pytorch(tmp_path):
  rng = np.random.default_rng(1)
  mean = _dirichlet(rng, (H, W))
  np.savez(tmp_path / "f0.npz", mean=np.moveaxis(mean, -1, 0))  # (K, H, W) as from torch.
  with pytest.raises(ValueError, match="sum to 1"):
    sources.precomputed_source(tmp_path).predict(None, None, index=0)
  pred = sources.precomputed_source(tmp_path, channels_first=True).predict(None, None, index=0)
  np.testing.assert_array_equal(np.asarray(pred.probs), mean)


@pytest.mark.parametrize("arrays, match", [
    ({"logits": np.zeros((H, W, K), np.float32)}, "expected arrays"),
    ({"mean": np.full((H, W, K), 3.0, np.float32)}, r"\[0, 1\]"),
    ({"mean": np.zeros((H, W, K), np.int32)}, "float"),
    ({"mean": np.full((H, W, K), np.nan, np.float32)}, "NaN"),
    ({"mean": np.full((H, W, K), 1 / K, np.float32),
      "var": np.zeros((H, W, K + 1), np.float32)}, "must match"),
    ({"mean": np.full((H, W, K), 1 / K, np.float32),
      "samples": np.full((2, H, W, K), 1 / K, np.float32)}, "both"),
])
def test_precomputed_source_rejects_bad_files(tmp_path, arrays, match):
  np.savez(tmp_path / "0.npz", **arrays)
  with pytest.raises((ValueError, TypeError), match=match):
    sources.precomputed_source(tmp_path).predict(None, None, index=0)


def test_precomputed_source_errors_on_missing_and_size_mismatch(tmp_path):
  with pytest.raises(FileNotFoundError):
    sources.precomputed_source(tmp_path / "nowhere")
  with pytest.raises(FileNotFoundError):
    sources.precomputed_source(tmp_path)
  sources.save_prediction(tmp_path / "0.npz", mean=np.full((H, W, K), 1 / K, np.float32))
  source = sources.precomputed_source(tmp_path)
  with pytest.raises(ValueError, match="index=i"):
    source.predict(None, None)
  with pytest.raises(IndexError):
    source.predict(None, None, index=5)
  with pytest.raises(ValueError, match="pixels"):
    source.predict(None, np.zeros((H + 1, W, 3), np.uint8), index=0)


# --- mc_moments: one pass, against a float64 two-pass reference ----------------------------------
def two_pass_float64(samples):
  x = np.asarray(samples, np.float64)
  mean = x.mean(axis=0)
  return mean, ((x - mean) ** 2).mean(axis=0)


def assert_moments_match(samples, atol=1e-6):
  mean, var = jaxfusion.mc_moments(samples)
  want_mean, want_var = two_pass_float64(samples)
  assert mean.dtype == var.dtype == jnp.float32
  assert mean.shape == var.shape == np.shape(samples)[1:]
  np.testing.assert_allclose(np.asarray(mean), want_mean, rtol=0, atol=atol)
  np.testing.assert_allclose(np.asarray(var), want_var, rtol=0, atol=atol)
  assert float(jnp.min(var)) >= 0.0


@pytest.mark.parametrize("num", [1, 2, 3, 32, 33, 70])   # one group, a group + 1, three groups
def test_mc_moments_one_hot_samples(num):
  rng = np.random.default_rng(num)
  labels = rng.integers(0, 5, (num, 3, 4))
  samples = np.eye(5, dtype=np.float32)[labels]
  samples[:, 0, 0] = np.eye(5, dtype=np.float32)[2]           # one pixel always one-hot on 2
  assert_moments_match(samples)
  _, var = jaxfusion.mc_moments(samples)
  assert np.all(np.asarray(var)[0, 0] == 0.0)                 # constant samples: exactly 0


@pytest.mark.parametrize("value", [0.0, 1e-30, 0.1, 1 / 3, 0.999999, 1.0])
def test_mc_moments_constant_samples_have_exactly_zero_variance(value):
  samples = np.full((37, 2, 3, 4), value, np.float32)
  mean, var = jaxfusion.mc_moments(samples)
  np.testing.assert_array_equal(np.asarray(mean), np.float32(value))
  np.testing.assert_array_equal(np.asarray(var), 0.0)


def test_mc_moments_hand_computed():
  samples = np.array([[[[1.0, 0.0]]], [[[0.0, 1.0]]], [[[0.5, 0.5]]], [[[0.5, 0.5]]]],
                     np.float32)                              # (M=4, 1, 1, K=2)
  mean, var = jaxfusion.mc_moments(samples)
  np.testing.assert_allclose(np.asarray(mean)[0, 0], [0.5, 0.5])
  np.testing.assert_allclose(np.asarray(var)[0, 0], [0.125, 0.125])   # (.25 + .25 + 0 + 0) / 4


def test_mc_moments_under_jit_and_vmap_and_rejects_bad_input():
  rng = np.random.default_rng(0)
  samples = rng.dirichlet(np.ones(3), (2, 5, 2, 3)).astype(np.float32)   # (B=2, M=5, 2, 3, 3)
  batched = jax.jit(jax.vmap(jaxfusion.mc_moments))(samples)
  for b in range(2):
    want = two_pass_float64(samples[b])
    for got, ref in zip(batched, want):
      np.testing.assert_allclose(np.asarray(got[b]), ref, atol=1e-6)
  with pytest.raises(ValueError, match="at least one sample"):
    jaxfusion.mc_moments(np.zeros((0, 2, 2, 3), np.float32))
  with pytest.raises(ValueError, match=r"\(M, H, W, K\)"):
    jaxfusion.mc_moments(np.zeros((2, 2, 3), np.float32))
  with pytest.raises(TypeError, match="float"):
    jaxfusion.mc_moments(np.zeros((2, 2, 2, 3), np.int32))


@hypothesis.settings(max_examples=40, deadline=None)
@hypothesis.given(
    num=st.integers(1, 40), k=st.integers(1, 4), seed=st.integers(0, 2**31 - 1),
    kind=st.sampled_from(["dirichlet", "peaked", "one_hot_mix", "tiny"]))
def test_mc_moments_property_equals_float64_two_pass(num, k, seed, kind):
  rng = np.random.default_rng(seed)
  shape = (num, 2, 3)
  if kind == "dirichlet":
    samples = rng.dirichlet(np.ones(k), shape)
  elif kind == "peaked":          # near one-hot softmax outputs: large values, tiny spread
    samples = rng.dirichlet(np.full(k, 0.05), shape)
  elif kind == "one_hot_mix":     # one-hot samples mixed with a few soft ones
    samples = np.eye(k)[rng.integers(0, k, shape)]
    soft = rng.random(shape) < 0.2
    samples[soft] = rng.dirichlet(np.ones(k), int(soft.sum()))
  else:                           # values near the float32 underflow edge
    samples = rng.random(shape + (k,)) * 1e-30
  assert_moments_match(samples.astype(np.float32))


def test_mc_moments_called_plainly_runs_one_compiled_program():
  # The README calls `jaxfusion.mc_moments(samples)` plainly: its arithmetic must run as one compiled
  # program (`sources._moments`), not op by op, and give what a call under `jax.jit` gives.
  samples = np.random.default_rng(7).dirichlet(np.ones(4), (5, 6, 7)).astype(np.float32)
  before = sources._moments._cache_size()  # pylint: disable=protected-access
  mean, var = jaxfusion.mc_moments(samples)
  after = sources._moments._cache_size()  # pylint: disable=protected-access
  assert after == before + 1
  jaxfusion.mc_moments(samples + 0.0)                       # same shape: no new compilation
  assert sources._moments._cache_size() == after  # pylint: disable=protected-access
  jit_mean, jit_var = jax.jit(jaxfusion.mc_moments)(samples)
  np.testing.assert_array_equal(np.asarray(mean), np.asarray(jit_mean))
  np.testing.assert_array_equal(np.asarray(var), np.asarray(jit_var))


@pytest.mark.parametrize("num", [31, 32, 33, 64, 97, 20_000])
def test_mc_moments_many_samples_compile_small_and_match_float64(num):
  # Full groups of 32 go through one scanned body and the rest unrolled: the compiled program must
  # not grow with M (M = 20 000 once took XLA past 18 GB when unrolled), and every split of M into
  # groups gives the float64 two-pass moments.
  samples = np.random.default_rng(num).dirichlet(np.ones(3), (num, 2, 3)).astype(np.float32)
  lowered = jax.jit(jaxfusion.mc_moments).lower(samples).as_text()
  assert len(lowered) < 200_000
  mean, var = jaxfusion.mc_moments(samples)
  np.testing.assert_allclose(np.asarray(mean), samples.astype(np.float64).mean(0), atol=1e-6)
  np.testing.assert_allclose(np.asarray(var), samples.astype(np.float64).var(0), atol=1e-6)
