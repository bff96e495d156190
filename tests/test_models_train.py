"""Training pieces: a few steps lower the loss; class weights, augmentation, masked loss."""

import dataclasses
import functools
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from models import checkpoint, net, train

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
  augment = functools.partial(train.augment, **dict(train.augment_kwargs(
      train.TrainConfig(blur_prob=1.0, zoom_max=1.5, noise_min=0.0, noise_max=0.05))))
  x, y = jax.jit(augment)(jax.random.key(0), jnp.asarray(images, jnp.float32) / 255.0,
                          jnp.asarray(labels))
  assert x.shape == images.shape and y.shape == labels.shape and y.dtype == jnp.int32
  assert float(x.min()) >= 0.0 and float(x.max()) <= 1.0
  assert set(np.unique(np.asarray(y))) <= set(range(K))


def test_gaussian_blur_is_identity_at_zero_and_preserves_constants_and_mass():
  rng = np.random.default_rng(0)
  image = jnp.asarray(rng.random((12, 10, 3)), jnp.float32)
  np.testing.assert_array_equal(np.asarray(train.gaussian_blur(image, jnp.float32(0.0))),
                                np.asarray(image))
  flat = jnp.full((12, 10, 3), 0.3, jnp.float32)
  np.testing.assert_allclose(np.asarray(train.gaussian_blur(flat, jnp.float32(1.2))), 0.3,
                             rtol=1e-5)
  # A centred impulse spreads into the separable normalised Gaussian (no mass reaches the
  # reflected border at this size).
  impulse = jnp.zeros((15, 15, 1)).at[7, 7, 0].set(1.0)
  out = np.asarray(train.gaussian_blur(impulse, jnp.float32(1.0)))[..., 0]
  taps = np.exp(-0.5 * np.arange(-3, 4) ** 2)
  taps /= taps.sum()
  expected = np.zeros((15, 15))
  expected[4:11, 4:11] = np.outer(taps, taps)
  np.testing.assert_allclose(out, expected, atol=1e-6)


def test_random_zoom_keeps_labels_aligned_with_colour():
  # Colour encodes the label, so after zooming each pixel's label must still match its colour
  # wherever the bilinear colour is not a blend across a boundary.
  images, labels = _toy_data(n=1, size=32)
  image = jnp.asarray(images[0], jnp.float32) / 255.0
  zi, zl = jax.jit(train.random_zoom, static_argnums=3)(jax.random.key(3), image,
                                                         jnp.asarray(labels[0]), 1.5)
  zi, zl = np.asarray(zi), np.asarray(zl)
  assert zi.shape == image.shape and zl.shape == labels[0].shape
  assert set(np.unique(zl)) <= set(np.unique(labels[0]))
  red = (zi[..., 0] > 0.8) & (zi[..., 2] < 0.25)
  blue = (zi[..., 2] > 0.8) & (zi[..., 0] < 0.25)
  assert red.any() and blue.any()
  assert np.all(zl[red] == 1) and np.all(zl[blue] == 2)
  # max_zoom = 1 is the identity.
  same_i, same_l = train.random_zoom(jax.random.key(0), image, jnp.asarray(labels[0]), 1.0)
  np.testing.assert_allclose(np.asarray(same_i), np.asarray(image), atol=1e-6)
  np.testing.assert_array_equal(np.asarray(same_l), labels[0])


def test_recipe_of_a_record_reproduces_its_settings(tmp_path):
  config = net.tiny_config(7)
  cfg = train.TrainConfig(steps=7, batch_size=3, learning_rate=1e-3, warmup_steps=2,
                          blur_prob=0.25, zoom_max=1.2)
  record = {"seed": 5, "eval_num_samples": 4, "train_config": cfg._asdict(),
            "data": {"height": 24, "width": 32, "train": {"num_images": 9},
                     "test": {"num_images": 2, "shift": 0.5}}}
  path = tmp_path / "segnet.json"
  path.write_text(json.dumps({"config": config.to_dict(), "record": record}))
  args = train.parse_args(["--recipe", str(path), "--steps", "3"])
  assert args.steps == 3  # explicit flags still win
  assert (args.seed, args.height, args.width, args.num_train, args.num_eval, args.shift) == (
      5, 24, 32, 9, 2, 0.5)
  assert (args.batch_size, args.lr, args.warmup, args.blur_prob, args.zoom_max) == (
      3, 1e-3, 2, 0.25, 1.2)
  assert (args.widths, args.strides, args.stem_width, args.aspp_rates, args.norm_groups) == (
      "8", "2", 8, "2", 4)
  # An old record without the newer augmentation fields means they were off.
  del record["train_config"]["blur_prob"], record["train_config"]["zoom_max"]
  path.write_text(json.dumps({"config": config.to_dict(), "record": record}))
  args = train.parse_args(["--recipe", str(path)])
  assert (args.blur_prob, args.zoom_max, args.noise_min, args.sensing) == (0.0, 1.0, 0.02, "off")
  # noise_max without noise_min: the level was drawn from [0, noise_max]; neither: fixed 0.02.
  del record["train_config"]["noise_min"]
  assert train.recipe_defaults({"config": config.to_dict(), "record": record})["noise_min"] == 0.0
  del record["train_config"]["noise_max"]
  record["data"]["sensing"] = "on"
  defaults = train.recipe_defaults({"config": config.to_dict(), "record": record})
  assert (defaults["noise_min"], defaults["noise_max"], defaults["sensing"]) == (0.02, 0.02, "on")
  with pytest.raises(ValueError, match="lacks field"):
    train.recipe_defaults({"config": config.to_dict(), "record": {}})


def test_shipped_recipe_replays_the_default_net_and_never_overwrites_it():
  recipe = checkpoint.WEIGHTS_DIR / "segnet.json"
  record = json.loads(recipe.read_text())
  args = train.parse_args(["--recipe", str(recipe)])
  config, cfg = record["config"], record["record"]["train_config"]
  assert (args.stem_width, args.widths, args.aspp_width, args.input_norm) == (
      config["stem_width"], ",".join(map(str, config["widths"])), config["aspp_width"], True)
  assert (args.steps, args.num_train, args.warmup, args.region_color_prob, args.texture_prob) == (
      cfg["steps"], record["record"]["data"]["train"]["num_images"], cfg["warmup_steps"],
      cfg["region_color_prob"], cfg["texture_prob"])
  # A training run writes elsewhere unless told to replace the packaged weights.
  for argv in ([], ["--recipe", str(recipe)]):
    out = train.parse_args(argv).out
    assert pathlib.Path(out).resolve() != checkpoint.PRETRAINED_PATH.resolve(), out


def _rbg(seed):
  """A key for the region-randomisation tests: any random numbers do, and rbg's ops compile
  several times faster than threefry's on a CPU."""
  return jax.random.key(seed, impl="rbg")


def _region_image(seed=0):
  """A 24×32 image of flat colours with a 3-class label map (blocks of 8 px)."""
  rng = np.random.default_rng(seed)
  labels = rng.integers(0, K, (3, 4)).repeat(8, 0).repeat(8, 1).astype(np.int32)
  image = rng.uniform(0.2, 0.8, (K, 3))[labels].astype(np.float32)
  return jnp.asarray(image), jnp.asarray(labels)


def test_region_recolor_is_identity_when_off_and_stays_in_range():
  image, labels = _region_image()
  same = train.region_recolor(_rbg(0), image, labels, num_classes=K, color_prob=0.0,
                              texture_prob=0.0)
  np.testing.assert_array_equal(np.asarray(same), np.asarray(image))
  for seed in range(5):
    out = np.asarray(train.region_recolor(_rbg(seed), image, labels, num_classes=K,
                                          color_prob=1.0, texture_prob=1.0))
    assert out.shape == image.shape and np.all(np.isfinite(out))
    assert out.min() >= 0.0 and out.max() <= 1.0


def test_region_recolor_gives_each_region_its_own_colour_transform():
  # Every class has the same colour; after recolouring, a colour maps to one output per
  # region (class × side of the cut), and different classes almost surely differ.
  image, labels = _region_image()
  image = jnp.full_like(image, 0.5).at[..., 0].set(0.7)
  out = np.asarray(train.region_recolor(_rbg(3), image, labels, num_classes=K,
                                        color_prob=1.0, texture_prob=0.0))
  distinct = {tuple(np.round(c, 5)) for c in out.reshape(-1, 3)}
  assert 2 <= len(distinct) <= 2 * K  # at most one colour per region
  for k in range(K):
    in_class = {tuple(np.round(c, 5)) for c in out[np.asarray(labels) == k]}
    assert len(in_class) <= 2  # one per side of the cut
  # Labels outside [0, K) are treated as background (class 0), not an index error.
  odd = labels.at[0, 0].set(-1)
  out = train.region_recolor(_rbg(3), image, odd, num_classes=K, color_prob=1.0,
                             texture_prob=0.0)
  assert np.all(np.isfinite(np.asarray(out)))


def test_region_texture_only_darkens_and_changes_some_pixels():
  image, labels = _region_image(1)
  out = np.asarray(train.region_recolor(_rbg(4), image, labels, num_classes=K,
                                        color_prob=0.0, texture_prob=1.0))
  assert np.all(out <= np.asarray(image) + 1e-7)
  changed = np.any(np.abs(out - np.asarray(image)) > 1e-3, axis=-1)
  assert 0.05 < changed.mean() < 1.0  # patterns have dark and untouched parts


def test_augment_with_region_randomisation_keeps_labels_and_range():
  images, labels = _toy_data(n=4, size=16)
  x = jnp.asarray(images, jnp.float32) / 255.0
  out_x, out_y = train.augment(_rbg(0), x, jnp.asarray(labels), region_color_prob=1.0,
                               texture_prob=0.5, num_classes=K)
  base_x, base_y = train.augment(_rbg(0), x, jnp.asarray(labels), num_classes=K)
  # Geometry uses the same keys either way: the labels are identical, the colours are not.
  np.testing.assert_array_equal(np.asarray(out_y), np.asarray(base_y))
  assert not np.allclose(np.asarray(out_x), np.asarray(base_x))
  assert float(out_x.min()) >= 0.0 and float(out_x.max()) <= 1.0


def test_recipe_carries_region_randomisation_and_input_norm(tmp_path):
  config = dataclasses.replace(net.tiny_config(7), input_norm=True)
  cfg = train.TrainConfig(steps=7, region_color_prob=0.5, texture_prob=0.25)
  record = {"seed": 1, "train_config": cfg._asdict(),
            "data": {"height": 24, "width": 32, "train": {"num_images": 9},
                     "test": {"num_images": 2, "shift": 1.0}}}
  path = tmp_path / "segnet.json"
  path.write_text(json.dumps({"config": config.to_dict(), "record": record}))
  args = train.parse_args(["--recipe", str(path)])
  assert (args.region_color_prob, args.texture_prob, args.input_norm) == (0.5, 0.25, True)
  # Old records (no such fields) mean off.
  del record["train_config"]["region_color_prob"], record["train_config"]["texture_prob"]
  old = net.tiny_config(7).to_dict()
  del old["input_norm"]
  defaults = train.recipe_defaults({"config": old, "record": record})
  assert (defaults["region_color_prob"], defaults["texture_prob"],
          defaults["input_norm"]) == (0.0, 0.0, False)
