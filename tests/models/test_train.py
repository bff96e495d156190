"""Training pieces: a few steps lower the loss; class weights, augmentation, masked loss."""

import dataclasses
import functools
import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from models import checkpoint, data, net, train

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


@pytest.mark.slow
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


@pytest.mark.slow
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


@pytest.mark.slow
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


# -- The configuration: flags, recipes and records, all derived from `train.Config`. --------------

RECIPES = {name: checkpoint.WEIGHTS_DIR / f"{name}.json"
           for name in ("segnet", "segnet_v1", "candidate_resnet18")}

# What the command produced before `Config` was the single source (captured by running the old
# `parse_args` and `main` up to training): the defaults, then per command line what differs.
OLD_DEFAULT = {
    "seed": 0, "height": 96, "width": 128, "num_train": 1600, "num_eval": 48, "shift": 1.0,
    "sensing": "off", "eval_samples": 16,
    "steps": 3000, "batch_size": 12, "learning_rate": 0.003, "warmup_steps": 60,
    "weight_decay": 0.0001, "clip_norm": 1.0, "class_weight_power": 0.5,
    "class_weight_max": 8.0, "color_strength": 1.0, "blur_prob": 0.0, "blur_max_sigma": 1.5,
    "noise_min": 0.02, "noise_max": 0.02, "zoom_max": 1.0, "region_color_prob": 0.0,
    "texture_prob": 0.0,
    "num_classes": 7, "stem_width": 24, "widths": (24, 48, 64, 96), "strides": (1, 2, 2, 1),
    "dilations": (1, 1, 1, 2), "blocks_per_stage": 1, "aspp_width": 64, "aspp_rates": (2, 4, 6),
    "dropout_rate": 0.3, "norm_groups": 8, "input_norm": False,
    "out": "outputs/segnet.msgpack", "cache": None, "save_every": 250,
}
SEGNET = {
    "num_train": 4000, "steps": 6500, "warmup_steps": 100, "blur_prob": 0.3, "noise_min": 0.0,
    "noise_max": 0.04, "region_color_prob": 0.5, "texture_prob": 0.5,
    "stem_width": 32, "widths": (32, 64, 96, 128), "aspp_width": 96, "input_norm": True,
}
OLD_COMMANDS = {
    "default": ([], {}),
    "quick": (["--quick"], {"steps": 40, "num_train": 64, "num_eval": 16}),
    "segnet": (["--recipe", str(RECIPES["segnet"])], SEGNET),
    "segnet_v1": (["--recipe", str(RECIPES["segnet_v1"])], {}),
    "candidate_resnet18": (["--recipe", str(RECIPES["candidate_resnet18"])], {
        "num_train": 2400, "sensing": "on", "steps": 1200, "warmup_steps": 100,
        "blur_prob": 0.5, "noise_min": 0.0, "noise_max": 0.04, "zoom_max": 1.4,
        "widths": (32, 64, 128, 192), "strides": (2, 2, 1, 1), "dilations": (1, 1, 2, 4),
        "blocks_per_stage": 2, "aspp_width": 128}),
    # The shipped net's own recorded command (less --cache and --out): the same as its recipe.
    "segnet_command": ("--num-train 4000 --steps 6500 --warmup 100 --stem-width 32 --widths "
                       "32,64,96,128 --aspp-width 96 --input-norm --region-color-prob 0.5 "
                       "--texture-prob 0.5 --blur-prob 0.3 --noise-min 0.0 --noise-max 0.04"
                       .split(), SEGNET),
    # Flags override a recipe.
    "segnet_override": (["--recipe", str(RECIPES["segnet"]), "--steps", "5", "--lr", "0.001",
                         "--no-input-norm", "--widths", "16,32,48,64", "--stem-width", "16",
                         "--aspp-width", "32"],
                        {**SEGNET, "steps": 5, "learning_rate": 0.001, "input_norm": False,
                         "widths": (16, 32, 48, 64), "stem_width": 16, "aspp_width": 32}),
    # Every other old flag; --quick only changes what is not given.
    "flags": ("--quick --batch-size 4 --weight-decay 0.01 --color-strength 0.5 --blur-max-sigma 2 "
              "--zoom-max 1.3 --sensing on --save-every 0 --height 48 --width 64 --num-eval 3 "
              "--eval-samples 2 --seed 7 --shift 0.5 --cache /tmp/c --strides 1,2,2,2 "
              "--dilations 1,1,1,1 --blocks-per-stage 2 --aspp-rates 1,2,3 --norm-groups 4 "
              "--dropout 0.1 --out /tmp/x.msgpack".split(), {
                  "seed": 7, "height": 48, "width": 64, "num_train": 64, "num_eval": 3,
                  "shift": 0.5, "sensing": "on", "eval_samples": 2, "batch_size": 4,
                  "blur_max_sigma": 2.0, "color_strength": 0.5, "steps": 40,
                  "weight_decay": 0.01, "zoom_max": 1.3, "aspp_rates": (1, 2, 3),
                  "blocks_per_stage": 2, "dilations": (1, 1, 1, 1), "dropout_rate": 0.1,
                  "norm_groups": 4, "strides": (1, 2, 2, 2), "out": "/tmp/x.msgpack",
                  "cache": "/tmp/c", "save_every": 0}),
}


def _flat(args):
  """Every setting of a parsed command line as `{name: value}` (sections flattened)."""
  config = dataclasses.asdict(args.config)
  flat = {k: v for k, v in config.items() if not isinstance(v, dict)}
  for name in ("train", "model"):
    flat.update(config[name])
  return {**flat, "out": args.out, "cache": args.cache, "save_every": args.save_every}


@pytest.mark.parametrize("case", sorted(OLD_COMMANDS))
def test_command_lines_and_shipped_recipes_give_the_configuration_they_gave_before(case):
  argv, changes = OLD_COMMANDS[case]
  expected = {**OLD_DEFAULT, **changes}
  got = _flat(train.parse_args(argv))
  assert got == expected
  assert {k: type(v) for k, v in got.items()} == {k: type(v) for k, v in expected.items()}


@pytest.mark.parametrize("name", sorted(RECIPES))
def test_a_config_survives_its_record_and_its_command_line(name):
  config = train.config_from_recipe(json.loads(RECIPES[name].read_text()))
  assert train.config_from_recipe(json.loads(json.dumps(train.config_to_recipe(config)))) == config
  assert train.parse_args(train.to_argv(config)).config == config
  # to_argv spells only what differs from the defaults.
  assert train.to_argv(train.Config()) == []


def test_written_records_keep_the_shipped_layout():
  recipe = json.loads(RECIPES["segnet"].read_text())
  written = train.config_to_recipe(train.config_from_recipe(recipe))
  assert written["config"] == recipe["config"]
  record = recipe["record"]
  assert written["record"]["train_config"] == record["train_config"]
  assert written["record"] == {
      "seed": record["seed"], "eval_num_samples": record["eval_num_samples"],
      "train_config": record["train_config"],
      "data": {"height": record["data"]["height"], "width": record["data"]["width"],
               "sensing": record["data"]["sensing"],
               "train": {"num_images": record["data"]["train"]["num_images"]},
               "test": {k: record["data"]["test"][k] for k in ("num_images", "shift")}}}
  # The training section is the dataclass itself.
  assert written["record"]["train_config"] == dataclasses.asdict(
      train.config_from_recipe(recipe).train)


def _recipe(**train_config):
  config = dataclasses.replace(net.tiny_config(7), input_norm=True)
  cfg = dataclasses.asdict(train.TrainConfig(steps=7, batch_size=3, learning_rate=1e-3,
                                             warmup_steps=2, blur_prob=0.25, zoom_max=1.2,
                                             region_color_prob=0.5, texture_prob=0.25))
  cfg.update(train_config)
  record = {"seed": 5, "eval_num_samples": 4, "train_config": cfg,
            "data": {"height": 24, "width": 32, "train": {"num_images": 9},
                     "test": {"num_images": 2, "shift": 0.5}}}
  return {"config": config.to_dict(), "record": record}


def test_recipe_fields_added_later_mean_what_the_code_before_them_did(tmp_path):
  recipe = _recipe()
  config = train.config_from_recipe(recipe)
  assert (config.seed, config.height, config.width, config.num_train, config.num_eval,
          config.shift, config.eval_samples) == (5, 24, 32, 9, 2, 0.5, 4)
  assert (config.train.steps, config.train.learning_rate, config.train.blur_prob,
          config.train.region_color_prob, config.model.widths, config.model.input_norm) == (
              7, 1e-3, 0.25, 0.5, (8,), True)
  # An old record without the newer augmentation fields means they were off; without
  # `sensing` it rendered without the camera model; without `input_norm`, raw input.
  tc = recipe["record"]["train_config"]
  for name in ("blur_prob", "blur_max_sigma", "zoom_max", "region_color_prob", "texture_prob",
               "clip_norm", "class_weight_power", "class_weight_max"):
    del tc[name]
  del recipe["config"]["input_norm"]
  config = train.config_from_recipe(recipe)
  assert (config.train.blur_prob, config.train.blur_max_sigma, config.train.zoom_max,
          config.train.region_color_prob, config.train.texture_prob, config.sensing,
          config.model.input_norm) == (0.0, 1.5, 1.0, 0.0, 0.0, "off", False)
  assert (config.train.clip_norm, config.train.class_weight_power,
          config.train.class_weight_max) == (1.0, 0.5, 8.0)
  # noise_max without noise_min: the level was drawn from [0, noise_max]; neither: fixed 0.02.
  del tc["noise_min"]
  assert train.config_from_recipe(recipe).train.noise_min == 0.0
  del tc["noise_max"], recipe["record"]["eval_num_samples"]
  recipe["record"]["data"]["sensing"] = "on"
  config = train.config_from_recipe(recipe)
  assert (config.train.noise_min, config.train.noise_max, config.sensing,
          config.eval_samples) == (0.02, 0.02, "on", 16)
  # The command line reads the same file the same way, and explicit flags still win.
  path = tmp_path / "segnet.json"
  path.write_text(json.dumps(recipe))
  args = train.parse_args(["--recipe", str(path), "--steps", "3"])
  assert args.config == dataclasses.replace(config, train=dataclasses.replace(config.train,
                                                                              steps=3))


def test_recipes_with_missing_or_unknown_fields_are_refused_clearly(tmp_path):
  with pytest.raises(ValueError, match="lacks field 'record.train_config'"):
    train.config_from_recipe({"config": net.tiny_config(7).to_dict(), "record": {}})
  recipe = _recipe()
  del recipe["record"]["seed"]
  with pytest.raises(ValueError, match="lacks field 'record.seed'"):
    train.config_from_recipe(recipe)
  recipe = _recipe()
  del recipe["record"]["train_config"]["steps"]
  with pytest.raises(ValueError, match="lacks field 'record.train_config.steps'"):
    train.config_from_recipe(recipe)
  with pytest.raises(ValueError, match="lacks field 'config'"):
    train.config_from_recipe({"record": _recipe()["record"]})
  with pytest.raises(ValueError, match=r"sets \['momentum'\], which this code does not know"):
    train.config_from_recipe(_recipe(momentum=0.9))
  recipe = _recipe()
  recipe["config"]["depth"] = 3
  with pytest.raises(ValueError, match="unknown SegNetConfig fields"):
    train.config_from_recipe(recipe)
  # On the command line, the same as a usage error.
  path = tmp_path / "segnet.json"
  path.write_text(json.dumps(_recipe(momentum=0.9)))
  with pytest.raises(SystemExit):
    train.parse_args(["--recipe", str(path)])


def test_set_sets_any_field_by_name_in_command_line_order():
  args = train.parse_args(["--recipe", str(RECIPES["segnet"]), "--set", "learning_rate=1e-3",
                           "--set", "widths=16,32,48,64", "--set", "input-norm=false",
                           "--set", "clip_norm=0.5", "--steps", "9", "--set", "steps=11"])
  assert (args.config.train.learning_rate, args.config.model.widths,
          args.config.model.input_norm, args.config.train.clip_norm,
          args.config.train.steps) == (1e-3, (16, 32, 48, 64), False, 0.5, 11)
  assert train.parse_args(["--set", "steps=11", "--steps", "9"]).config.train.steps == 9
  for bad in ("nonsense=1", "steps", "steps=x", "sensing=maybe", "num_classes=3"):
    with pytest.raises(SystemExit):
      train.parse_args(["--set", bad])
  with pytest.raises(SystemExit):  # The architecture's own checks, as a usage error.
    train.parse_args(["--norm-groups", "5"])


def test_help_lists_a_flag_for_every_field():
  text = train.build_parser().format_help()
  for leaf in train._leaves():
    assert leaf.flag in text and f"[{leaf.name};" in text
  for flag in ("--recipe", "--quick", "--out", "--set", "--cache", "--save-every", "--lr",
               "--warmup", "--dropout", "--no-input-norm"):
    assert flag in text
  assert "num_classes" not in text  # set by the data


def test_quick_and_recipe_runs_never_overwrite_the_packaged_weights():
  for argv in ([], ["--quick"], ["--recipe", str(RECIPES["segnet"])]):
    out = train.parse_args(argv).out
    assert out == "outputs/segnet.msgpack"
    assert pathlib.Path(out).resolve() != checkpoint.PRETRAINED_PATH.resolve(), out


@pytest.mark.slow
def test_train_and_evaluate_writes_a_checkpoint_whose_record_replays_its_config(tmp_path,
                                                                              monkeypatch):
  rng = np.random.default_rng(0)

  def load_domain(domain, num_images, *, height, width, seed, shift=1.0, cache_dir=None,
                  sensing=True):
    labels = rng.integers(0, 7, (num_images, height, width)).astype(np.int32)
    return (labels[..., None] * 30).repeat(3, -1).astype(np.uint8), labels

  monkeypatch.setattr(data, "load_domain", load_domain)
  # The evaluation has tests of its own; here only its place in the record matters.
  monkeypatch.setattr(train.evaluate, "evaluate_arrays",
                      lambda *a, **k: {"summary": {"mc_miou": 0.5}})
  config = train.replace_fields(train.Config(), {
      "steps": 2, "batch_size": 2, "num_train": 4, "num_eval": 2, "height": 16, "width": 16,
      "eval_samples": 2, "seed": 3, "sensing": "on", **{
          k: v for k, v in dataclasses.asdict(net.tiny_config(7)).items()
          if k != "num_classes"}})
  out = tmp_path / "run" / "segnet.msgpack"
  record = train.train_and_evaluate(config, out, save_every=1, progress=False)
  loaded = checkpoint.load(out, class_names=data.dataset_class_names())
  assert loaded.config == config.model and loaded.metadata["record"] == record
  assert record["command"] == " ".join(["python -m models.train", *train.to_argv(config)])
  assert record["data"]["heldout"] == {"domain": "train", "num_images": 2, "seed": 10_003}
  assert record["eval"]["test_shifted"] == {"mc_miou": 0.5}
  assert not out.with_suffix(".partial.msgpack").exists()
  sidecar = json.loads(out.with_suffix(".json").read_text())
  assert sidecar["record"] == record
  assert train.config_from_recipe(sidecar) == config
  assert train.parse_args(["--recipe", str(out.with_suffix(".json"))]).config == config
