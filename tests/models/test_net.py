"""The segmentation net and its MC-dropout sampling: shapes, keys, determinism, bad input."""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfusion
from models import net, sampling

H, W, K = 16, 16, 7
M = 4  # One M for all tests: each distinct M is a separate compilation.


@pytest.fixture(scope="module")
def tiny():
  # Weights from an RBG key: XLA on CPU compiles threefry's initialiser several times slower,
  # and nothing here depends on which weights (test_train inits with threefry).
  graphdef, params = net.init(net.tiny_config(K), key=jax.random.key(0, impl="rbg"))
  return graphdef, params


def with_config(config, tiny):
  """`(graphdef, params)` of `config`, a variant of `tiny_config(K)` whose parameters have the
  same structure (dropout rate, input standardisation): the tiny net's weights under the
  variant's graph, so that no second initialiser has to compile."""
  graphdef, abstract = net.abstract_params(config)
  params = tiny[1]
  assert jax.tree_util.tree_structure(abstract) == jax.tree_util.tree_structure(params)
  return graphdef, params


# Dropout off, one compiled forward pass per graph.
apply_deterministic = jax.jit(functools.partial(net.apply, deterministic=True), static_argnums=0)


@pytest.fixture(scope="module")
def image():
  return np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)


def test_config_round_trips_through_json_dict():
  config = net.SegNetConfig(widths=(16, 32), strides=(2, 2), dilations=(1, 2), stem_width=16,
                            aspp_width=16)
  assert net.SegNetConfig.from_dict(config.to_dict()) == config
  assert config.output_stride == 8


def test_resnet18_config_is_the_deeper_deeplab_variant():
  config = net.resnet18_config()
  assert config.output_stride == 8 and config.num_dropout_layers == 9
  _, params = net.abstract_params(config)
  assert 2_800_000 < net.count_params(params) < 3_000_000
  assert net.count_params(net.abstract_params(net.SegNetConfig())[1]) == 493_503


@pytest.mark.parametrize("bad", [
    dict(widths=(8, 16), strides=(1,), dilations=(1, 2)),
    dict(dropout_rate=1.0),
    dict(num_classes=1),
    dict(norm_groups=5),
])
def test_config_rejects_inconsistent_architectures(bad):
  with pytest.raises(ValueError):
    net.SegNetConfig(**bad)


def test_params_are_the_only_state_and_count_is_positive(tiny):
  _, params = tiny
  leaves = jax.tree_util.tree_leaves(params)
  assert all(leaf.dtype == jnp.float32 for leaf in leaves)
  assert 0 < net.count_params(params) < 50_000


def test_logits_have_input_size_for_any_resolution(tiny):
  graphdef, params = tiny
  for h, w in [(H, W), (20, 28)]:
    probs = sampling.deterministic_probs(graphdef, params, jnp.zeros((2, h, w, 3)))
    assert probs.shape == (2, h, w, K) and probs.dtype == jnp.float32


def test_mc_samples_shapes_and_simplex(tiny, image):
  graphdef, params = tiny
  samples = sampling.mc_samples(graphdef, params, jax.random.key(1), image, num_samples=M)
  assert samples.shape == (M, H, W, K) and samples.dtype == jnp.float32
  np.testing.assert_allclose(np.asarray(samples).sum(-1), 1.0, atol=1e-5)
  mean, var = jaxfusion.mc_moments(samples)
  assert mean.shape == var.shape == (H, W, K)
  assert float(var.max()) > 0.0


def test_same_key_same_samples_and_different_keys_differ(tiny, image):
  graphdef, params = tiny
  a = sampling.mc_samples(graphdef, params, jax.random.key(1), image, num_samples=4)
  b = sampling.mc_samples(graphdef, params, jax.random.key(1), image, num_samples=4)
  c = sampling.mc_samples(graphdef, params, jax.random.key(2), image, num_samples=4)
  np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  assert float(jnp.abs(a - c).max()) > 1e-4
  # The M samples of one call differ from each other too (independent dropout masks).
  assert float(jnp.abs(a[0] - a[1]).max()) > 1e-4


def test_dropout_off_is_identical_for_every_key(tiny, image):
  graphdef, params = tiny
  apply_fn = sampling.deterministic_apply_fn(graphdef)
  a = apply_fn(params, jax.random.key(1), image)
  b = apply_fn(params, jax.random.key(2), image)
  np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  np.testing.assert_allclose(np.asarray(sampling.deterministic_probs(graphdef, params, image)),
                             np.asarray(a), atol=1e-5)


def test_zero_dropout_rate_makes_mc_samples_identical(tiny, image):
  config = dataclasses.replace(net.tiny_config(K), dropout_rate=0.0)
  graphdef, params = with_config(config, tiny)
  samples = sampling.mc_samples(graphdef, params, jax.random.key(3), image, num_samples=M)
  np.testing.assert_array_equal(np.asarray(samples[0]), np.asarray(samples[1]))


def test_vmap_over_keys_equals_a_loop_over_keys(tiny, image):
  graphdef, params = tiny
  m = M
  key = jax.random.key(5)
  vmapped = sampling.mc_samples(graphdef, params, key, image, num_samples=m)
  apply_fn = jax.jit(sampling.stochastic_apply_fn(graphdef))
  looped = np.stack([np.asarray(apply_fn(params, k, image)) for k in jax.random.split(key, m)])
  np.testing.assert_allclose(np.asarray(vmapped), looped, atol=1e-5)


def test_batch_over_frames_matches_single_frames(tiny, image):
  graphdef, params = tiny
  images = np.stack([image, image[::-1]])
  key = jax.random.key(7)
  batch = sampling.mc_samples_batch(graphdef, params, key, images, num_samples=M)
  assert batch.shape == (2, M, H, W, K)
  for b, k in enumerate(jax.random.split(key, 2)):
    single = sampling.mc_samples(graphdef, params, k, images[b], num_samples=M)
    np.testing.assert_allclose(np.asarray(batch[b]), np.asarray(single), atol=1e-5)
  det = sampling.deterministic_probs(graphdef, params, images)
  assert det.shape == (2, H, W, K)


def test_uint8_and_float_inputs_agree(tiny, image):
  graphdef, params = tiny
  a = sampling.deterministic_probs(graphdef, params, image)
  b = sampling.deterministic_probs(graphdef, params, image.astype(np.float32) / 255.0)
  np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-5)


@pytest.mark.parametrize("bad, error, match", [
    (np.zeros((H, W), np.uint8), ValueError, "RGB image"),
    (np.zeros((H, W, 4), np.uint8), ValueError, "3 colour channels"),
    (np.zeros((3, H, W), np.uint8), ValueError, "channels-first"),
    (np.zeros((H, W, 3), np.int32), TypeError, "uint8"),
    (np.zeros((H, W, 3), bool), TypeError, "uint8"),
    (np.full((H, W, 3), 200.0, np.float32), ValueError, r"\[0, 1\]"),
])
def test_bad_images_raise_clear_errors(tiny, bad, error, match):
  graphdef, params = tiny
  with pytest.raises(error, match=match):
    sampling.mc_samples(graphdef, params, jax.random.key(0), bad, num_samples=M)


def test_mc_samples_rejects_batches_and_bad_m(tiny, image):
  graphdef, params = tiny
  with pytest.raises(ValueError, match="mc_samples_batch"):
    sampling.mc_samples(graphdef, params, jax.random.key(0), image[None], num_samples=M)
  with pytest.raises(ValueError, match="num_samples"):
    sampling.mc_samples(graphdef, params, jax.random.key(0), image, num_samples=0)


def test_standardize_gives_zero_mean_unit_std_and_stays_finite_on_flat_images():
  rng = np.random.default_rng(1)
  x = jnp.asarray(rng.uniform(0, 1, (2, 8, 10, 3)), jnp.float32)
  z = np.asarray(net.standardize(x))
  np.testing.assert_allclose(z.mean(axis=(1, 2)), 0.0, atol=1e-5)
  np.testing.assert_allclose(z.std(axis=(1, 2)), 1.0, atol=1e-4)
  flat = np.asarray(net.standardize(jnp.zeros((1, 4, 4, 3))))
  assert np.all(flat == 0.0)


def test_input_norm_makes_the_net_blind_to_a_global_colour_cast(tiny, image):
  config = dataclasses.replace(net.tiny_config(K), input_norm=True)
  graphdef, params = with_config(config, tiny)
  x = jnp.asarray(image, jnp.float32)[None] / 255.0
  cast = x * jnp.array([0.6, 0.8, 1.1]) + jnp.array([0.1, 0.0, -0.05])  # per-channel affine
  a = apply_deterministic(graphdef, params, None, x)
  b = apply_deterministic(graphdef, params, None, cast)
  np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=2e-4)
  # Without it the same cast changes the logits.
  graphdef0, params0 = tiny
  a0 = apply_deterministic(graphdef0, params0, None, x)
  b0 = apply_deterministic(graphdef0, params0, None, cast)
  assert float(jnp.max(jnp.abs(a0 - b0))) > 1e-2
  # Old configs without the field load as input_norm=False.
  old = net.tiny_config(K).to_dict()
  del old["input_norm"]
  assert net.SegNetConfig.from_dict(old).input_norm is False


def _conv_batches(jaxpr) -> list:
  """Leading (batch) size of every convolution's output in a jaxpr, in program order."""
  sizes = []
  for eqn in jaxpr.eqns:
    if eqn.primitive.name == "conv_general_dilated":
      sizes.append(eqn.outvars[0].aval.shape[0])
    for sub in jax.core.subjaxprs(eqn) if hasattr(jax.core, "subjaxprs") else ():
      sizes += _conv_batches(sub)
    for param in eqn.params.values():
      inner = getattr(param, "jaxpr", None)
      if inner is not None and hasattr(inner, "eqns"):
        sizes += _conv_batches(inner)
  return sizes


@pytest.mark.slow
def test_mc_samples_share_the_layers_before_the_first_dropout(input_norm=True):
  # The stem and the first block run once per image (batch 1), every later convolution once per
  # sample (batch M), and the samples are those of M independent full passes with the same keys.
  config = dataclasses.replace(net.tiny_config(), widths=(8, 8), strides=(2, 1),
                               dilations=(1, 1), input_norm=input_norm)
  graphdef, params = net.init(config, key=jax.random.key(0))
  image = np.random.default_rng(1).integers(0, 256, (16, 24, 3), dtype=np.uint8)
  key, m = jax.random.key(5), 6
  samples = sampling.mc_samples(graphdef, params, key, image, num_samples=m)
  x = sampling.prepare_images(image)[None]
  one_pass = lambda k: jax.nn.softmax(net.apply(graphdef, params, k, x, deterministic=False)[0],
                                      axis=-1)
  keys = jax.random.split(key, m)
  # Bit for bit the M full passes vmapped in one program (the sampler before the split) ...
  @jax.jit
  def vmapped_full_passes(p, k, im):
    return jax.vmap(lambda kk: jax.nn.softmax(
        net.apply(graphdef, p, kk, im[None], deterministic=False)[0], axis=-1))(
            jax.random.split(k, m))
  np.testing.assert_array_equal(np.asarray(samples),
                                np.asarray(vmapped_full_passes(params, key, x[0])))
  # ... and M separate full passes up to float32 rounding, which this small random net amplifies
  # (one full pass eagerly and under jit differ by ~2e-4 here).
  separate = np.stack([np.asarray(jax.jit(one_pass)(k)) for k in keys])
  np.testing.assert_allclose(np.asarray(samples), separate, atol=1e-3)
  assert not np.allclose(np.asarray(samples[0]), np.asarray(samples[1]))   # masks differ
  jaxpr = jax.make_jaxpr(
      lambda k, im: sampling._mc_samples(graphdef, params, k, im, num_samples=m))(  # pylint: disable=protected-access
          key, sampling.prepare_images(image)).jaxpr
  batches = _conv_batches(jaxpr)
  # Stem (1 conv) + first block (2 convs, and a projection shortcut when its shape changes).
  shared = 1 + 2 + (1 if config.widths[0] != config.stem_width or config.strides[0] != 1 else 0)
  assert batches[:shared] == [1] * shared, batches
  assert batches[shared:] and all(b == m for b in batches[shared:]), batches


@pytest.mark.slow
def test_apply_is_from_shared_after_shared():
  graphdef, params = net.init(net.tiny_config(), key=jax.random.key(2))
  x = jnp.asarray(np.random.default_rng(3).random((2, 12, 20, 3)), jnp.float32)
  for key, deterministic in ((jax.random.key(4), False),):
    whole = net.apply(graphdef, params, key, x, deterministic=deterministic)
    parts = net.apply_from_shared(graphdef, params, key, net.apply_shared(graphdef, params, x),
                                  (12, 20), deterministic=deterministic)
    np.testing.assert_array_equal(np.asarray(whole), np.asarray(parts))
