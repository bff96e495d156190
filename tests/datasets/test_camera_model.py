"""The camera model of the embedded world: each effect against a hand-computed or NumPy
reference, the AE loop's range and lag, and `SensingConfig.off()` against the plain pipeline."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import ndimage

from jaxfusion.camera import Camera
from jaxfusion.datasets import (appearance, camera_model, raycast, sensor_noise, synthetic,
                                trajectories)
from jaxfusion.datasets import primitives as P
from jaxfusion.datasets.camera_model import CameraState, SensingConfig

SIZE = dict(height=24, width=32)  # the size and sequence of test_synthetic: shared compiles
CAM = Camera(30.0, 30.0, 15.0, 10.0)  # 31 × 21 images have their centre pixel on the axis
H, W = 21, 31


def _state(exposure=1.0, gain=1.0, wb=(1.0, 1.0, 1.0), noise_scale=1.0, motion=None):
  motion = camera_model.still_state().motion if motion is None else motion
  return CameraState(np.float32(exposure), np.float32(gain), np.asarray(wb, np.float32),
                     np.float32(noise_scale), np.asarray(motion, np.float32))


def _texture(h=H, w=W, seed=0):
  return np.random.default_rng(seed).uniform(0.1, 0.9, (h, w, 3)).astype(np.float32)


# ----------------------------------------------------------------------------- the whole pipeline


@pytest.fixture(scope="module")
def sequences():
  on = synthetic.make_sequence("office", 0, num_frames=4, **SIZE)
  off = synthetic.make_sequence("office", 0, num_frames=4, sensing=SensingConfig.off(), **SIZE)
  return on, off


def test_off_reproduces_the_plain_realism_pipeline(sequences):
  _, off = sequences
  # Reference: the pre-sensing renderer, composed from the unchanged parts.
  world = synthetic.make_scene("office", seed=0)
  camera = synthetic.default_camera(**SIZE)
  poses = trajectories.trajectory(world.layout.room, 0, 4)
  keys = jax.random.split(jax.random.PRNGKey(0 * 7 + 0), 4)
  sizes = synthetic.trajectory_tile_sizes(world, poses, camera, **SIZE)
  packed = raycast.pack(world.primitives, step=64)
  for t, (T, k) in enumerate(zip(poses, keys)):
    tiles = raycast.tile_lists(packed, T, camera, tile=synthetic.TILE, min_sizes=sizes, **SIZE)
    hits = raycast.cast(packed, T, camera, tiles=tiles, tile=synthetic.TILE, **SIZE)
    k_depth, k_image = jax.random.split(k)
    depth = sensor_noise.noisy_depth(k_depth, hits.depth, hits.normal, hits.view_dir)
    rgb = sensor_noise.noisy_image(k_image, synthetic._shade(packed, hits, world.lighting))
    np.testing.assert_array_equal(off.rgb[t], np.asarray(jnp.round(rgb * 255.0)).astype(np.uint8))
    np.testing.assert_array_equal(off.depth[t], np.asarray(depth))
  assert "camera_states" not in off.info


def test_sensing_changes_colour_only(sequences):
  on, off = sequences
  np.testing.assert_array_equal(on.depth, off.depth)
  np.testing.assert_array_equal(on.labels, off.labels)
  np.testing.assert_array_equal(on.instances, off.instances)
  np.testing.assert_array_equal(on.T_world_cam, off.T_world_cam)
  assert np.abs(on.rgb.astype(int) - off.rgb.astype(int)).mean() > 2
  states = on.info["camera_states"]
  assert len(states["exposure"]) == 4 and on.info["sensing"] == SensingConfig().as_dict()


def test_sequences_are_deterministic(sequences):
  on, _ = sequences
  again = synthetic.make_sequence("office", 0, num_frames=4, **SIZE)
  np.testing.assert_array_equal(on.rgb, again.rgb)
  assert on.info["camera_states"] == again.info["camera_states"]


def test_sample_views_keep_poses_and_labels():
  on_rgb, on_labels = synthetic.sample_views("train", 2, seed=3, **SIZE)
  off_rgb, off_labels = synthetic.sample_views("train", 2, seed=3, sensing=SensingConfig.off(),
                                               **SIZE)
  assert on_rgb.shape == (2, 24, 32, 3) and on_rgb.dtype == np.uint8
  np.testing.assert_array_equal(on_labels, off_labels)
  assert not np.array_equal(on_rgb, off_rgb)
  again, _ = synthetic.sample_views("train", 2, seed=3, **SIZE)
  np.testing.assert_array_equal(on_rgb, again)


def test_config_is_validated():
  with pytest.raises(ValueError, match="exposure_max"):
    SensingConfig(exposure_min=2.0, exposure_max=1.0).validate()
  with pytest.raises(ValueError, match="speed"):
    SensingConfig(speed=0.0).validate()
  with pytest.raises(ValueError, match="vignetting"):
    SensingConfig(vignetting=1.5).validate()
  with pytest.raises(TypeError, match="enabled"):
    SensingConfig(enabled="yes").validate()
  with pytest.raises(TypeError, match="SensingConfig"):
    synthetic.make_sequence("office", 0, num_frames=1, sensing={"gloss": 0.0}, **SIZE)
  with pytest.raises(TypeError, match="SensingConfig"):
    synthetic.sample_views("train", 1, sensing=SensingConfig.off()._asdict(), **SIZE)
  assert SensingConfig.off().enabled is False


# ----------------------------------------------------------------------------- auto-exposure


@settings(max_examples=200, deadline=None)
@given(log_e=st.floats(-5, 5), metered=st.floats(0, 10), set_point=st.floats(0.01, 0.99),
       dt=st.floats(1e-3, 10))
def test_ae_exposure_stays_within_its_range(log_e, metered, set_point, dt):
  config = SensingConfig()
  out = camera_model.ae_step(log_e, metered, set_point, dt=dt, config=config)
  assert np.log(config.exposure_min) - 1e-12 <= out <= np.log(config.exposure_max) + 1e-12


def test_ae_follows_a_brightness_step_with_its_lag():
  config = SensingConfig(ae_time_constant=0.5)
  dt = 0.25
  alpha = 1.0 - np.exp(-dt / config.ae_time_constant)
  # A settled camera (E = 1 gives the set-point) when the scene turns half as bright.
  log_e, history = 0.0, []
  for _ in range(12):
    metered = 0.5 * 0.42 * np.exp(log_e)
    log_e = camera_model.ae_step(log_e, metered, 0.42, dt=dt, config=config)
    history.append(log_e)
  # Hand-computed: the gap to log 2 shrinks by (1 − α) per frame.
  expected = np.log(2.0) * (1.0 - (1.0 - alpha) ** np.arange(1, 13))
  np.testing.assert_allclose(history, expected, rtol=1e-9)
  assert 0.0 < history[0] < np.log(2.0) / 2  # a lag: not there after one frame


def test_sequence_exposure_and_white_balance_stay_in_range():
  config = SensingConfig(exposure_drift=2.0, wb_drift=1.0)  # strong drift pushes the clips
  seq = synthetic.make_sequence("office", 0, num_frames=4, sensing=config, **SIZE)
  states = seq.info["camera_states"]
  e = np.asarray(states["exposure"])
  assert np.all((e >= config.exposure_min - 1e-6) & (e <= config.exposure_max + 1e-6))
  wb = np.log(np.asarray(states["white_balance"]))
  assert np.all(np.abs(wb) <= config.wb_range + 1e-6) and np.all(wb[:, 1] == 0)
  t, g = np.asarray(states["exposure_time_s"]), np.asarray(states["gain"])
  np.testing.assert_allclose(t * g, e * config.exposure_time, rtol=1e-4)
  assert np.all(t <= config.max_exposure_time + 1e-9) and np.all(g >= 1.0)


def test_split_exposure_uses_time_first_then_gain():
  config = SensingConfig(exposure_time=0.01, max_exposure_time=0.03)
  assert camera_model.split_exposure(2.0, config) == pytest.approx((0.02, 1.0))
  assert camera_model.split_exposure(6.0, config) == pytest.approx((0.03, 2.0))


def test_ou_process_is_stationary_with_its_correlation():
  x = camera_model.ou_process(np.random.default_rng(0), 20000, 0.5, 0.2, 2.0)[:, 0]
  assert np.std(x) == pytest.approx(0.2, rel=0.08)
  lag1 = np.corrcoef(x[:-1], x[1:])[0, 1]
  assert lag1 == pytest.approx(np.exp(-0.5 / 2.0), abs=0.03)


# ----------------------------------------------------------------------------- motion blur


def test_velocity_of_a_known_move():
  T_cur = trajectories.look_at((0.0, 0.0, 1.0), (1.0, 0.0, 1.0))  # looking along world +x
  T_prev = T_cur.copy()
  T_prev[:3, 3] -= [0.1, 0.0, 0.0]  # it came 0.1 m forward in 0.2 s
  v, w = camera_model.velocity(T_prev, T_cur, 0.2)
  np.testing.assert_allclose(v, [0.0, 0.0, 0.5], atol=1e-6)  # +z: forward in the camera
  np.testing.assert_allclose(w, 0.0, atol=1e-6)


def test_motion_blur_is_zero_when_still():
  img = _texture()
  depth = np.full((H, W), 2.0, np.float32)
  out = camera_model.motion_blur(img, depth, CAM, camera_model.still_state().motion)
  np.testing.assert_allclose(np.asarray(out), img, atol=1e-6)
  still = camera_model.motion_from_velocity(np.zeros(3), np.zeros(3), 0.03)
  np.testing.assert_array_equal(still, camera_model.still_state().motion)


def test_motion_blur_length_matches_the_pan():
  img = np.zeros((H, W, 3), np.float32)
  img[10, 15] = 1.0  # one bright point on the optical axis
  depth = np.full((H, W), 3.0, np.float32)
  omega, t_exp = 20.0, 0.01  # a fast pan about the camera's y axis
  motion = camera_model.motion_from_velocity(np.zeros(3), [0.0, omega, 0.0], t_exp)
  out = np.asarray(camera_model.motion_blur(img, depth, CAM, motion))[..., 0]
  cols = np.nonzero(out.max(0) > 1e-6)[0]
  length = CAM.fx * np.tan(omega * t_exp)  # 6.2 px
  assert cols.max() - cols.min() == pytest.approx(length, abs=1.5)
  assert out[10].sum() > 0.95 * out.sum()  # (almost) no vertical smear
  assert out.sum() == pytest.approx(1.0, rel=0.15)  # about conserved (K taps, bilinear)
  flat = np.asarray(camera_model.motion_blur(np.full((H, W, 3), 0.3, np.float32), depth, CAM,
                                             motion))
  np.testing.assert_allclose(flat, 0.3, rtol=1e-6)


def test_motion_blur_grows_with_speed():
  img = _texture()
  depth = np.full((H, W), 2.0, np.float32)
  err = []
  for speed in (0.0, 0.5, 1.0, 2.0, 4.0):
    motion = camera_model.motion_from_velocity([speed, 0.0, 0.0], [0.0, 0.0, 0.0], 0.033)
    out = np.asarray(camera_model.motion_blur(img, depth, CAM, motion))
    err.append(np.abs(out - img)[:, 4:-4].mean())
  assert err[0] < 1e-6 and np.all(np.diff(err) > 0)


def test_sequence_motion_follows_the_trajectory():
  """Frames of a faster walk (fewer frames per loop at the same speed) are blurrier."""
  config = SensingConfig(noise_jitter=0.0, shot_noise=0.0, read_noise=0.0, exposure_drift=0.0,
                         wb_drift=0.0)
  slow = synthetic.make_sequence("office", 0, num_frames=4, sensing=config, **SIZE)
  fast = synthetic.make_sequence("office", 0, num_frames=4,
                                 sensing=config._replace(speed=4.0), **SIZE)
  assert fast.info["camera_states"]["frame_interval_s"] < slow.info["camera_states"][
      "frame_interval_s"]
  sharpness = lambda s: np.abs(np.diff(s.rgb.astype(float), axis=2)).mean()
  assert sharpness(fast) < sharpness(slow)


# ----------------------------------------------------------------------------- defocus


def test_defocus_sigma_grows_with_distance_beyond_focus():
  z = np.array([1.5, 2.0, 3.0, 5.0, 10.0], np.float32)
  s = np.asarray(camera_model.defocus_sigma(z, 100.0, aperture=0.01, focus_distance=1.5,
                                       optical_blur=0.5))
  assert s[0] == pytest.approx(0.5)
  coc = 0.01 * 100.0 * np.abs(1 / 1.5 - 1 / z)  # thin lens, in pixels
  np.testing.assert_allclose(s, np.sqrt(0.25 + (coc / 4) ** 2), rtol=1e-5)
  assert np.all(np.diff(s) > 0)


def test_gaussian_levels_match_scipy():
  img = _texture()
  for sigma in camera_model.BLUR_LEVELS[1:]:
    ours = np.asarray(camera_model._gaussian_blur(jnp.asarray(img), sigma))
    ref = ndimage.gaussian_filter(img, (sigma, sigma, 0), mode="nearest", truncate=3.0)
    # scipy truncates at int(3σ + 0.5); both normalise their kernels.
    np.testing.assert_allclose(ours, ref, atol=2e-3 if sigma < 1 else 1e-5)


def test_defocused_image_loses_contrast_with_distance():
  yy, xx = np.mgrid[:H, :W]
  checker = np.repeat((((yy // 2) + (xx // 2)) % 2).astype(np.float32)[..., None], 3, -1)
  config = SensingConfig(aperture=0.05, focus_distance=1.0, optical_blur=0.0, vignetting=0.0,
                         shot_noise=0.0, read_noise=0.0)
  contrast = []
  for z in (1.0, 2.0, 4.0, 8.0):
    depth = np.full((H, W), z, np.float32)
    rgb, _ = camera_model.camera_image(jax.random.PRNGKey(0), checker * 0.8, depth, CAM, _state(),
                                  config)
    contrast.append(np.asarray(rgb)[6:-6, 6:-6].std())
  assert contrast[0] == pytest.approx(0.4, rel=1e-4)  # in focus, no blur: the checker itself
  assert np.all(np.diff(contrast) < 0)


# ----------------------------------------------------------------------------- highlights


def _floor_highlight(eye_x):
  """Glossy lobe on the floor z = 0 along y = 0 for a lamp at (0, 0, 2) and an eye at
  (eye_x, 0, 1); returns the points' x and the lobe."""
  x = np.linspace(-3.0, 3.0, 601, dtype=np.float32)
  p = np.stack([x, np.zeros_like(x), np.zeros_like(x)], -1)
  eye = np.array([eye_x, 0.0, 1.0], np.float32)
  view = (p - eye) / np.linalg.norm(p - eye, axis=-1, keepdims=True)
  normal = np.tile([0.0, 0.0, 1.0], (len(x), 1)).astype(np.float32)
  spec = camera_model.glossy_highlight(
      normal, p, view, np.ones(len(x), np.float32), np.array([0.0, 0.0, 2.0], np.float32),
      np.ones(3, np.float32), np.array([0.0, 0.0, -1.0], np.float32), np.zeros(3, np.float32),
      strength=1.0, shininess=60.0)
  return x, np.asarray(spec)[:, 0]


def test_highlight_sits_at_the_mirror_point_and_moves_with_the_viewpoint():
  peaks = []
  for eye_x in (1.5, -0.9):
    x, spec = _floor_highlight(eye_x)
    # The mirror reflection of the lamp (height 2) seen from the eye (height 1): x = eye_x·2/3.
    assert x[np.argmax(spec)] == pytest.approx(eye_x * 2 / 3, abs=0.02)
    peaks.append(x[np.argmax(spec)])
  assert abs(peaks[0] - peaks[1]) > 1.0


def test_highlight_is_zero_on_matte_material_and_off():
  x = np.zeros((4, 3), np.float32)
  normal = np.tile([0.0, 0.0, 1.0], (4, 1)).astype(np.float32)
  view = np.tile([0.0, 0.0, -1.0], (4, 1)).astype(np.float32)
  args = (normal, x, view)
  light = (np.array([0, 0, 2.0], np.float32), np.ones(3, np.float32),
           np.array([0, 0, -1.0], np.float32), np.ones(3, np.float32))
  glossy = camera_model.glossy_highlight(*args, np.ones(4, np.float32), *light, strength=1.0,
                                    shininess=60.0)
  assert np.all(np.asarray(glossy) > 0.5)
  matte = camera_model.glossy_highlight(*args, np.zeros(4, np.float32), *light, strength=1.0,
                                   shininess=60.0)
  off = camera_model.glossy_highlight(*args, np.ones(4, np.float32), *light, strength=0.0,
                                 shininess=60.0)
  assert np.all(np.asarray(matte) == 0) and np.all(np.asarray(off) == 0)


# ----------------------------------------------------------------------------- vignetting, noise


def test_vignetting_is_one_at_the_centre_and_falls_radially():
  gain = np.asarray(camera_model.vignetting_gain(CAM, H, W, 0.4))
  assert gain[10, 15] == pytest.approx(1.0)
  corner_tan2 = (15 / 30.0) ** 2 + (10 / 30.0) ** 2
  assert gain[0, 0] == pytest.approx(0.6 + 0.4 / (1 + corner_tan2) ** 2, rel=1e-6)
  r = np.hypot(*np.mgrid[-10:11, -15:16])
  order = np.argsort(r.ravel(), kind="stable")
  assert np.all(np.diff(gain.ravel()[order])[np.diff(r.ravel()[order]) > 1e-9] < 0)
  np.testing.assert_array_equal(np.asarray(camera_model.vignetting_gain(CAM, H, W, 0.0)), 1.0)


@pytest.mark.parametrize("gain, noise_scale", [(1.0, 1.0), (3.0, 0.5)])
def test_noise_std_matches_the_configured_level(gain, noise_scale):
  config = SensingConfig(optical_blur=0.0, aperture=0.0, vignetting=0.0, shot_noise=1e-3,
                         read_noise=0.01)
  flat = np.full((H, W, 3), 0.25, np.float32)
  depth = np.full((H, W), 2.0, np.float32)
  state = _state(exposure=2.0, gain=gain, noise_scale=noise_scale)
  rgb, metered = camera_model.camera_image(jax.random.PRNGKey(1), flat, depth, CAM, state, config)
  x = 0.5  # exposed signal
  expected = noise_scale * np.sqrt(1e-3 * gain * x + (0.01 * gain) ** 2)
  rgb = np.asarray(rgb)
  assert rgb.std() == pytest.approx(expected, rel=0.06)  # 3σ of the estimate from H·W·3 pixels
  assert rgb.mean() == pytest.approx(x, abs=4 * expected / np.sqrt(H * W * 3))
  assert float(metered) == pytest.approx(x, rel=1e-5)


def test_white_balance_scales_channels():
  config = SensingConfig(optical_blur=0.0, aperture=0.0, vignetting=0.0, shot_noise=0.0,
                         read_noise=0.0)
  img = _texture()
  depth = np.full((H, W), 2.0, np.float32)
  rgb, _ = camera_model.camera_image(jax.random.PRNGKey(0), img, depth, CAM,
                                _state(exposure=0.8, wb=(1.1, 1.0, 0.9)), config)
  np.testing.assert_allclose(np.asarray(rgb), np.clip(img * 0.8 * [1.1, 1.0, 0.9], 0, 1),
                             rtol=1e-5)


# ----------------------------------------------------------------------------- texture filter


def test_pixel_footprint_by_hand():
  fp = camera_model.pixel_footprint(np.array([2.0, 4.0, 4.0]), np.array([1.0, 1.0, 0.25]), 100.0,
                                    0.5)
  np.testing.assert_allclose(np.asarray(fp), [0.01, 0.02, 0.04], rtol=1e-6)


@pytest.mark.parametrize("texture_id", [P.STRIPES, P.CHECKER, P.WOOD, P.NOISE, P.SCREEN])
def test_texture_detail_fades_with_the_footprint(texture_id):
  n = 4000
  rng = np.random.default_rng(texture_id)
  p_local = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
  ids = np.full(n, texture_id, np.int32)
  scale = np.full(n, 8.0, np.float32)
  color, color2 = np.tile([0.8, 0.2, 0.1], (n, 1)), np.tile([0.1, 0.3, 0.9], (n, 1))
  args = (p_local, ids, scale, color.astype(np.float32), color2.astype(np.float32))
  texture = jax.jit(appearance.texture)
  point = np.asarray(texture(*args))
  np.testing.assert_allclose(np.asarray(texture(*args, footprint=np.zeros(n, np.float32))),
                             point, atol=1e-6)
  spread = [np.asarray(texture(*args, footprint=np.full(n, fp, np.float32))).std(0).sum()
            for fp in (0.0, 0.01, 0.02, 0.05, 1.0)]
  assert np.all(np.diff(spread) < 0) and spread[-1] < 1e-3 * spread[0]  # float32 rounding


def test_camera_effects_summary(sequences):
  from jaxfusion.lab import data as cli
  on, _ = sequences
  effects = cli.camera_effects(on, SensingConfig())
  assert all(v.shape == (4,) for v in effects.values())
  assert np.all(effects["motion_blur_px"] > 0)  # the walk never stops
  assert np.all(effects["defocus_sigma_px"] >= SensingConfig().optical_blur - 1e-6)
  np.testing.assert_allclose(effects["exposure"], on.info["camera_states"]["exposure"])


def test_motion_taps_cover_the_streak():
  assert [camera_model.motion_taps(x) for x in (0.0, 0.2, 1.0, 1.5, 6.2, 7.0, 100.0)] == [
      2, 2, 2, 4, 8, 8, camera_model.MAX_MOTION_TAPS]
  depth = np.full((H, W), 3.0, np.float32)
  omega, t_exp = [0.0, 20.0, 0.0], 0.01  # the pan of test_motion_blur_length_matches_the_pan
  motion = camera_model.exposure_motion(np.zeros(3), omega, t_exp, depth, CAM)
  assert motion.shape == (16, 4, 4)  # the streak: 6.2 px on the axis, 8.6 px at the border
  np.testing.assert_allclose(motion[-1], camera_model.motion_from_velocity(np.zeros(3), omega,
                                                                      t_exp)[-1], atol=1e-6)


def test_entry_points_reject_bad_input():
  img, depth = _texture(), np.full((H, W), 2.0, np.float32)
  with pytest.raises(ValueError, match="radiance"):
    camera_model.camera_image(jax.random.PRNGKey(0), img[..., :2], depth, CAM, _state(),
                         SensingConfig())
  with pytest.raises(ValueError, match="CameraState"):
    camera_model.camera_image(jax.random.PRNGKey(0), img, depth, CAM,
                         _state()._replace(motion=np.eye(4)), SensingConfig())
  with pytest.raises(ValueError, match="dt"):
    camera_model.velocity(np.eye(4), np.eye(4), 0.0)
  with pytest.raises(ValueError, match="speed"):
    camera_model.frame_interval(np.tile(np.eye(4), (3, 1, 1)), 0.0)
  with pytest.raises(ValueError, match="taps"):
    camera_model.motion_from_velocity(np.zeros(3), np.zeros(3), 0.01, taps=0)
