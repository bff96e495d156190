"""Training pieces: a few steps lower the loss; class weights, augmentation, masked loss."""

import functools

import jax
import jax.numpy as jnp
import numpy as np

from models import net, train

K = 3


def _toy_data(n=8, size=16, seed=0):
  """Images whose label is readable from the colour: red → 1, blue → 2, else 0."""
  rng = np.random.default_rng(seed)
  labels = rng.integers(0, K, (n, size // 4, size // 4)).repeat(4, 1).repeat(4, 2)
  palette = np.array([[128, 128, 128], [230, 30, 30], [30, 30, 230]], np.uint8)
  images = palette[labels] + rng.integers(0, 20, (n, size, size, 3)).astype(np.uint8)
  return images.astype(np.uint8), labels.astype(np.int32)


@functools.partial(jax.jit, static_argnums=0)
def _eval_loss_jit(graphdef, params, images, labels):
  logits = net.apply(graphdef, params, None, images.astype(jnp.float32) / 255.0,
                     deterministic=True)
  return train.weighted_cross_entropy(logits, labels, jnp.ones(K))


def _eval_loss(graphdef, params, images, labels):
  """Weighted CE with dropout off and no augmentation: a noise-free measure of fit."""
  return float(_eval_loss_jit(graphdef, params, jnp.asarray(images), jnp.asarray(labels)))


def test_a_few_steps_lower_the_loss():
  config = net.tiny_config(K)
  graphdef, params = net.init(config, key=jax.random.key(0))
  images, labels = _toy_data()
  # The toy labels are defined by colour, so no colour randomisation here.
  cfg = train.TrainConfig(steps=20, batch_size=4, learning_rate=1e-2, warmup_steps=2,
                          color_strength=0.0)
  trained, losses = train.fit(graphdef, params, images, labels, key=jax.random.key(1), cfg=cfg,
                              progress=False)
  assert losses.shape == (20,) and np.all(np.isfinite(losses))
  before = _eval_loss(graphdef, params, images, labels)
  after = _eval_loss(graphdef, trained, images, labels)
  assert after < 0.9 * before, (before, after)
  # fit trains a copy: the caller's params are untouched (train_step donates its inputs).
  assert _eval_loss(graphdef, params, images, labels) == before


def test_class_weights_favour_rare_classes_and_average_to_one():
  labels = np.zeros((1, 10, 10), np.int32)
  labels[0, :2] = 1          # 20 %
  labels[0, 2, :1] = 2       # 1 %
  weights = train.class_weights(labels, 4, power=0.5, max_weight=8.0)
  assert weights.shape == (4,) and weights.dtype == np.float32
  assert weights[2] > weights[1] > weights[0]
  freq = np.bincount(labels.ravel(), minlength=4) / labels.size
  np.testing.assert_allclose((weights * freq).sum(), 1.0, rtol=1e-5)
  assert weights[3] == weights.max()  # absent class: clipped maximum


def test_cross_entropy_ignores_unlabelled_pixels():
  logits = jnp.zeros((1, 2, 2, K)).at[0, 0, 0, 1].set(5.0)
  labels = jnp.array([[[1, -1], [-1, -1]]], jnp.int32)
  loss = train.weighted_cross_entropy(logits, labels, jnp.ones(K))
  expected = -jax.nn.log_softmax(logits[0, 0, 0])[1]
  np.testing.assert_allclose(float(loss), float(expected), rtol=1e-5)


def test_augment_keeps_shapes_ranges_and_label_set():
  images, labels = _toy_data(n=2)
  x, y = jax.jit(train.augment)(jax.random.key(0), jnp.asarray(images, jnp.float32) / 255.0,
                                jnp.asarray(labels))
  assert x.shape == images.shape and y.shape == labels.shape and y.dtype == jnp.int32
  assert float(x.min()) >= 0.0 and float(x.max()) <= 1.0
  assert set(np.unique(np.asarray(y))) <= set(range(K))
