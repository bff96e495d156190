"""View-dependent sensing: what a real camera does between scene radiance and the 8-bit image.

A clean ray caster shows a surface the same in every view; a real camera does not. This module
adds, per frame and at render time, the camera effects that make one view of a surface differ
from the next, each with a physical model and a documented parameter in `SensingConfig`:

* **Auto-exposure (AE) with lag**: the camera meters the centre-weighted mean brightness of the
  frame it has just taken and moves its exposure towards a set-point with a time constant
  (`ae_time_constant`); the set-point itself drifts slowly (`exposure_drift`, an
  Ornstein–Uhlenbeck process over time, as metering shifts with scene content). The exposure
  stays within `[exposure_min, exposure_max]`. It is split like a real AE: longer exposure
  time first (up to `max_exposure_time`), analog gain after that (which amplifies noise).
* **White-balance drift**: the red and blue channel gains drift slowly (`wb_drift`, clipped to
  `± wb_range` in log gain). The illuminant's colour is not corrected away (it is part of the
  domain gap), only the camera's gains wander.
* **Motion blur** from the camera's own velocity: the image is averaged over the poses the
  camera passes through during the exposure time (K poses between the frame's pose and
  `exposure_time / frame_interval` of the way back to the previous pose; K a power of two
  with at least one pose per pixel of the longest streak, up to `MAX_MOTION_TAPS`), using the
  per-pixel flow those poses induce through the depth. A still camera gives no blur.
* **Defocus**: a thin lens focused at `focus_distance` with an entrance pupil of `aperture`
  metres blurs a surface at depth z with a circle of confusion of
  `aperture · fx · |1/focus_distance − 1/z|` pixels (fx: focal length in pixels), on top of the
  lens/demosaicing blur `optical_blur`. Farther than the focus distance, blur grows with depth.
* **Resolution loss with distance**: a pixel integrates the light over its footprint on the
  surface, which grows with distance and obliquity; texture detail finer than that averages
  to its mean colour (`texture_filter`), where a one-sample ray caster would alias it into
  speckle.
* **Glossy highlights**: a Blinn-Phong lobe `gloss · material_gloss · (n·h)^shininess` from the
  room's lamp and sun, on glossy materials only (`appearance.GLOSS`): the highlight moves with
  the viewpoint, and it saturates under a long exposure.
* **Vignetting**: natural `cos⁴θ` falloff of a wide-angle lens, partly corrected by lens design:
  the gain is `1 − vignetting + vignetting · cos⁴θ` (1 on the optical axis).
* **Sensor noise**: signal-dependent shot noise plus read noise (Poisson–Gaussian model):
  `var = shot_noise · gain · x + (read_noise · gain)²` on the raw signal x ∈ [0, 1], times a
  per-frame factor `exp(noise_jitter · N(0, 1))` (sensor temperature, ISP denoising strength);
  the result is white-balanced, clipped and quantised to 8 bits by the renderer.

The effects act on colour only; depth keeps its own sensor model
(`sensor_noise.noisy_depth`) and the labels stay exact. Time enters through the frame interval:
a trajectory sampled at T frames is walked at a mean speed of `speed` m/s, so consecutive frames
lie `step / speed` seconds apart.

`SensingConfig.off()` turns everything off: the renderer then produces exactly the images of
the plain `realism` pipeline (`sensor_noise.noisy_image`).

Shape legend: H×W pixels, T frames, K poses within one exposure.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion.camera import Camera

# Poses averaged over one exposure for motion blur: the default, and the most `exposure_motion`
# uses (it picks a power of two ≥ the streak length in pixels + 1, at least 2).
MOTION_TAPS = 8
MAX_MOTION_TAPS = 32
# Blur levels (Gaussian σ in pixels) between which the depth-dependent blur is interpolated;
# the largest is the most blur any pixel gets.
BLUR_LEVELS = (0.0, 0.5, 1.0, 2.0, 4.0)
# Rec. 709 luma weights, for metering.
_LUMA = (0.2126, 0.7152, 0.0722)
# Width of the AE's centre-weighted metering window, as a fraction of the image diagonal.
_METER_SIGMA = 0.3


class SensingConfig(NamedTuple):
  """The camera model of the synthetic world (all fields are plain Python numbers).

  Attributes:
    enabled: False turns every effect off (see `off`).
    speed: mean speed of the camera along a trajectory in m/s (a slow hand-held scan); sets
      the time between frames and hence the velocities behind motion blur and the AE lag.
    angular_speed: RMS pan rate in rad/s of the random velocities given to the independent
      views of `synthetic.sample_views` (which have no trajectory): that of the three
      trajectories walked at `speed` (0.51 rad/s over layout seeds 0–4 at 40 and 60 frames).
    ae_target: mean brightness in [0, 1] the AE aims for (centre-weighted mean luma of the
      output); 0.42 is the mean of the clean renderer, so the AE keeps its nominal look.
    ae_time_constant: seconds for the AE to close 63 % of the gap to its set-point.
    exposure_min: lowest relative exposure the AE can set (1 = nominal).
    exposure_max: highest relative exposure.
    exposure_drift: stationary standard deviation of the AE set-point's log drift.
    wb_drift: stationary standard deviation of the log red/blue white-balance gains.
    wb_range: clip of the log white-balance gains.
    drift_time_constant: correlation time in seconds of the exposure and white-balance drift.
    exposure_time: exposure time in seconds at nominal exposure.
    max_exposure_time: longest exposure time; beyond it the AE raises the analog gain.
    aperture: entrance-pupil diameter of the lens in metres (a 12 mm f/2 lens: 6 mm).
    focus_distance: distance in metres the lens is focused at.
    optical_blur: σ in pixels of the lens and demosaicing blur at every depth.
    texture_filter: σ in pixels of the pixel's own integration plus the sensor's optical
      low-pass filter, applied to the procedural textures (`appearance.texture`): texture
      detail finer than a pixel fades to its mean, so far and grazing surfaces lose their
      patterns (0: point samples, which alias instead).
    vignetting: strength in [0, 1] of the cos⁴ falloff (0: none, 1: the full cos⁴θ).
    gloss: strength of the glossy highlight (multiplies each material's `gloss`).
    shininess: Blinn-Phong exponent of the glossy lobe (larger: smaller, sharper highlights).
    shot_noise: shot-noise variance per unit signal at unit gain.
    read_noise: read-noise standard deviation at unit gain.
    noise_jitter: standard deviation of the per-frame log noise level.
  """
  enabled: bool = True
  speed: float = 0.5
  angular_speed: float = 0.5
  ae_target: float = 0.42
  ae_time_constant: float = 0.5
  exposure_min: float = 0.5
  exposure_max: float = 2.5
  exposure_drift: float = 0.12
  wb_drift: float = 0.04
  wb_range: float = 0.12
  drift_time_constant: float = 4.0
  exposure_time: float = 0.012
  max_exposure_time: float = 0.033
  aperture: float = 0.006
  focus_distance: float = 1.5
  optical_blur: float = 0.7
  texture_filter: float = 0.5
  vignetting: float = 0.35
  gloss: float = 0.5
  shininess: float = 60.0
  shot_noise: float = 4e-4
  read_noise: float = 0.006
  noise_jitter: float = 0.3

  @classmethod
  def off(cls) -> "SensingConfig":
    """A config that turns every effect off (the plain `realism` renderer)."""
    return cls(enabled=False)

  def validate(self) -> "SensingConfig":
    """Checks the values; returns the config.

    Raises:
      TypeError: `enabled` is not a bool.
      ValueError: a value is out of its range.
    """
    if not isinstance(self.enabled, (bool, np.bool_)):
      raise TypeError(f"SensingConfig.enabled must be a bool; got {self.enabled!r}")
    for name in self._fields[1:]:
      value = getattr(self, name)
      if not isinstance(value, (int, float, np.floating, np.integer)) or not np.isfinite(value):
        raise ValueError(f"SensingConfig.{name} must be a finite number; got {value!r}")
      if value < 0:
        raise ValueError(f"SensingConfig.{name} must be ≥ 0; got {value}")
    for name in ("speed", "ae_time_constant", "drift_time_constant", "exposure_min",
                 "focus_distance", "max_exposure_time", "ae_target"):
      if getattr(self, name) <= 0:
        raise ValueError(f"SensingConfig.{name} must be > 0; got {getattr(self, name)}")
    if self.exposure_max < self.exposure_min:
      raise ValueError(f"SensingConfig.exposure_max ({self.exposure_max}) must be ≥ "
                       f"exposure_min ({self.exposure_min})")
    if self.vignetting > 1 or self.ae_target >= 1:
      raise ValueError("SensingConfig.vignetting must be ≤ 1 and ae_target < 1; got "
                       f"{self.vignetting}, {self.ae_target}")
    return self

  def as_dict(self) -> dict:
    """The config as JSON-serialisable plain values."""
    return {k: (bool(v) if k == "enabled" else float(v)) for k, v in self._asdict().items()}


class CameraState(NamedTuple):
  """The camera's settings for one frame (a pytree of arrays).

  Attributes:
    exposure: scalar relative exposure E (= exposure time / nominal time × gain).
    gain: scalar analog gain (≥ 1 once the exposure time is at its maximum).
    white_balance: `(3,)` channel gains (green = 1).
    noise_scale: scalar per-frame factor on the noise standard deviation.
    motion: `(K, 4, 4)` the camera's poses during the exposure, in the frame's camera frame
      (`T_cam_tap`); all identity for a still camera.
  """
  exposure: jax.Array
  gain: jax.Array
  white_balance: jax.Array
  noise_scale: jax.Array
  motion: jax.Array


def still_state(exposure: float = 1.0, *, taps: int = MOTION_TAPS) -> CameraState:
  """A still camera at the given exposure, neutral white balance and nominal noise."""
  return CameraState(np.float32(exposure), np.float32(1.0), np.ones(3, np.float32),
                     np.float32(1.0), np.tile(np.eye(4, dtype=np.float32), (taps, 1, 1)))


# ----------------------------------------------------------------------------- time processes


def frame_interval(poses, speed: float) -> float:
  """Seconds between consecutive frames of a closed trajectory walked at `speed` m/s.

  Args:
    poses: `(T, 4, 4)` camera-to-world poses (a loop: the last frame is followed by the first).
    speed: mean speed in m/s.

  Returns:
    The mean step length divided by `speed`; 1/30 s when the camera centre does not move.
  """
  if not speed > 0:
    raise ValueError(f"speed must be > 0; got {speed}")
  eyes = np.asarray(poses, np.float64)[:, :3, 3]
  if len(eyes) < 2:
    return 1.0 / 30.0
  step = float(np.mean(np.linalg.norm(np.roll(eyes, -1, axis=0) - eyes, axis=-1)))
  return step / speed if step > 1e-9 else 1.0 / 30.0


def ou_process(rng: np.random.Generator, num_steps: int, dt: float, sigma: float, tau: float,
               dims: int = 1) -> np.ndarray:
  """A stationary Ornstein–Uhlenbeck process sampled every `dt` seconds.

  Args:
    rng: NumPy generator.
    num_steps: T samples.
    dt: sampling interval in seconds.
    sigma: stationary standard deviation.
    tau: correlation time in seconds.
    dims: independent components.

  Returns:
    `(T, dims) float64` with `x_0 ~ N(0, σ²)`, `x_{t+1} = ρ x_t + √(1 − ρ²) σ ε`,
    `ρ = exp(−dt / τ)`.
  """
  if num_steps < 0 or not dt > 0 or not tau > 0 or not sigma >= 0:
    raise ValueError(f"ou_process needs num_steps ≥ 0, dt > 0, tau > 0, sigma ≥ 0; got "
                     f"{num_steps}, {dt}, {tau}, {sigma}")
  rho = float(np.exp(-dt / tau))
  eps = rng.normal(size=(num_steps, dims))
  x = np.zeros((num_steps, dims))
  if num_steps:
    x[0] = sigma * eps[0]
  for t in range(1, num_steps):
    x[t] = rho * x[t - 1] + np.sqrt(1.0 - rho * rho) * sigma * eps[t]
  return x


def ae_step(log_exposure: float, metered: float, set_point: float, *, dt: float,
            config: SensingConfig) -> float:
  """One update of the auto-exposure loop.

  The camera has just taken a frame at `exp(log_exposure)` and metered its brightness; it moves
  its log exposure a fraction `1 − exp(−dt / ae_time_constant)` of the way towards the
  exposure that would have hit `set_point`, within `[exposure_min, exposure_max]`.

  Args:
    log_exposure: log of the exposure the metered frame was taken with.
    metered: that frame's metered brightness (> 0).
    set_point: the brightness the AE aims for.
    dt: seconds to the next frame.
    config: `SensingConfig`.

  Returns:
    The log exposure of the next frame.
  """
  if not dt > 0:
    raise ValueError(f"dt must be > 0; got {dt}")
  alpha = 1.0 - np.exp(-dt / config.ae_time_constant)
  step = np.log(set_point) - np.log(max(float(metered), 1e-4))
  return float(np.clip(log_exposure + alpha * step, np.log(config.exposure_min),
                       np.log(config.exposure_max)))


def split_exposure(exposure: float, config: SensingConfig) -> tuple:
  """`(exposure_time_s, gain)` of a relative exposure: time first, then gain."""
  t = min(exposure * config.exposure_time, config.max_exposure_time)
  return t, max(exposure * config.exposure_time / t, 1.0)


def _rotvec_to_matrix(w) -> np.ndarray:
  theta = float(np.linalg.norm(w))
  if theta < 1e-12:
    return np.eye(3)
  k = np.asarray(w, np.float64) / theta
  K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
  return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def _matrix_to_rotvec(R) -> np.ndarray:
  R = np.asarray(R, np.float64)
  cos = np.clip((np.trace(R) - 1.0) / 2.0, -1.0, 1.0)
  theta = float(np.arccos(cos))
  axis = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
  if theta < 1e-9:
    return axis / 2.0
  return axis * theta / (2.0 * np.sin(theta))


def motion_from_velocity(v_cam, omega_cam, exposure_time: float, *,
                         taps: int = MOTION_TAPS) -> np.ndarray:
  """The camera's poses during one exposure, moving backwards in time from the frame's pose.

  Args:
    v_cam: `(3,)` linear velocity in m/s, in the camera frame.
    omega_cam: `(3,)` angular velocity (rotation vector per second), in the camera frame.
    exposure_time: seconds.
    taps: K poses, evenly spaced from the frame's pose (tap 0) back over the exposure.

  Returns:
    `(K, 4, 4) float32` `T_cam_tap`; all identity when both velocities are zero.
  """
  if taps < 1 or exposure_time < 0:
    raise ValueError(f"need taps ≥ 1 and exposure_time ≥ 0; got {taps}, {exposure_time}")
  out = np.tile(np.eye(4), (taps, 1, 1))
  for k in range(1, taps):
    s = -exposure_time * k / max(taps - 1, 1)
    out[k, :3, :3] = _rotvec_to_matrix(np.asarray(omega_cam, np.float64) * s)
    out[k, :3, 3] = np.asarray(v_cam, np.float64) * s
  return out.astype(np.float32)


@jax.jit
def streak_length(depth, camera: Camera, T_end):
  """Longest motion-blur streak in pixels: the largest flow to the end-of-exposure pose
  `T_end (4, 4)` (`T_cam_tap`) over the image `depth (H, W)`."""
  du, dv = _tap_flow(_backproject(depth, camera), camera, jnp.asarray(T_end, jnp.float32))
  return jnp.max(jnp.hypot(du, dv))


def motion_taps(streak_px: float) -> int:
  """Poses per exposure for a streak of `streak_px` pixels: the smallest power of two
  ≥ `streak_px + 1`, within `[2, MAX_MOTION_TAPS]` (so samples lie ≤ 1 px apart)."""
  need = max(2.0, float(streak_px) + 1.0)
  return int(min(MAX_MOTION_TAPS, 1 << int(np.ceil(np.log2(need)))))


def exposure_motion(v_cam, omega_cam, exposure_time: float, depth, camera: Camera) -> np.ndarray:
  """`motion_from_velocity` with as many poses as the frame's longest streak needs.

  Args:
    v_cam: `(3,)` linear velocity in m/s (camera frame).
    omega_cam: `(3,)` angular velocity in rad/s (camera frame).
    exposure_time: seconds.
    depth: `(H, W)` the frame's z-depth.
    camera: intrinsics.

  Returns:
    `(K, 4, 4) float32` with `K = motion_taps(streak_length(...))`.
  """
  end = motion_from_velocity(v_cam, omega_cam, exposure_time, taps=2)[-1]
  streak = float(streak_length(depth, camera, end))
  return motion_from_velocity(v_cam, omega_cam, exposure_time, taps=motion_taps(streak))


def velocity(T_prev, T_cur, dt: float) -> tuple:
  """`(v_cam, omega_cam)` of a camera that moved from `T_prev` to `T_cur` in `dt` seconds.

  Both are expressed in the frame of `T_cur` (camera-to-world poses).
  """
  if not dt > 0:
    raise ValueError(f"dt must be > 0; got {dt}")
  rel = np.linalg.inv(np.asarray(T_cur, np.float64)) @ np.asarray(T_prev, np.float64)
  return -rel[:3, 3] / dt, -_matrix_to_rotvec(rel[:3, :3]) / dt


def random_velocity(rng: np.random.Generator, T_world_cam, config: SensingConfig) -> tuple:
  """A random hand-held velocity for an independent view, in the camera frame.

  Linear: horizontal world direction uniform, speed `|N(0, speed²)|`; angular: a pan about the
  world vertical with rate `N(0, angular_speed²)` and a tilt about the camera x axis with rate
  `N(0, (angular_speed / 2)²)`.

  Returns:
    `(v_cam (3,), omega_cam (3,))`.
  """
  R = np.asarray(T_world_cam, np.float64)[:3, :3]
  heading = rng.uniform(0.0, 2.0 * np.pi)
  v_world = abs(rng.normal(0.0, config.speed)) * np.array([np.cos(heading), np.sin(heading), 0.0])
  omega_world = np.array([0.0, 0.0, rng.normal(0.0, config.angular_speed)])
  omega_cam = R.T @ omega_world + np.array([rng.normal(0.0, config.angular_speed / 2), 0.0, 0.0])
  return R.T @ v_world, omega_cam


# ----------------------------------------------------------------------------- image effects


def pixel_footprint(distance, cos_incidence, fx, sigma_px):
  """σ in metres of a pixel's filter on a surface.

  Args:
    distance: `(N,)` distance from the camera centre to the surface point in metres.
    cos_incidence: `(N,)` |cos| of the angle between the ray and the surface normal.
    fx: focal length in pixels.
    sigma_px: σ of the filter in pixels.

  Returns:
    `(N,)` `sigma_px · distance / (fx · √cos)`: the geometric mean of the footprint's extent
    across (`distance / fx`) and along (`distance / (fx cos)`) the slant.
  """
  return sigma_px * distance / (fx * jnp.sqrt(jnp.maximum(cos_incidence, 0.05)))


@jax.jit
def glossy_highlight(normal, p_world, view_dir, gloss, lamp_pos, lamp_color, sun_dir, sun_color,
                     *, strength, shininess):
  """The glossy (Blinn-Phong) lobe of the room's lamp and sun.

  Args:
    normal: `(N, 3)` unit normals facing the camera.
    p_world: `(N, 3)` surface points.
    view_dir: `(N, 3)` unit ray directions (camera → surface).
    gloss: `(N,)` material glossiness in [0, 1].
    lamp_pos: `(3,)` point light position.
    lamp_color: `(3,)` point light colour.
    sun_dir: `(3,)` unit direction the directional light travels.
    sun_color: `(3,)` its colour.
    strength: scalar `SensingConfig.gloss`.
    shininess: scalar Blinn-Phong exponent.

  Returns:
    `(N, 3) float32` added radiance (≥ 0), largest where the half vector between the light and
    the viewer meets the normal, i.e. at the mirror reflection of the light.
  """
  to_eye = -view_dir
  to_lamp = lamp_pos - p_world
  dist2 = jnp.sum(to_lamp * to_lamp, -1, keepdims=True)
  to_lamp = to_lamp * jax.lax.rsqrt(jnp.maximum(dist2, 1e-6))

  def lobe(to_light, color, falloff):
    half = to_light + to_eye
    half = half * jax.lax.rsqrt(jnp.maximum(jnp.sum(half * half, -1, keepdims=True), 1e-12))
    facing = jnp.sum(normal * to_light, -1, keepdims=True) > 0
    n_h = jnp.maximum(jnp.sum(normal * half, -1, keepdims=True), 0.0)
    return jnp.where(facing, n_h ** shininess, 0.0) * color * falloff

  spec = (lobe(to_lamp, lamp_color, 1.0 / (1.0 + 0.08 * dist2))
          + lobe(-sun_dir * jnp.ones_like(p_world), sun_color, 1.0))
  return (strength * gloss[:, None] * spec).astype(jnp.float32)


@functools.partial(jax.jit, static_argnames=("height", "width"))
def vignetting_gain(camera: Camera, height: int, width: int, strength):
  """`(H, W) float32` lens gain `1 − a + a·cos⁴θ`, θ the angle of the pixel's ray to the axis."""
  u = (jnp.arange(width, dtype=jnp.float32) - camera.cx) / camera.fx
  v = (jnp.arange(height, dtype=jnp.float32) - camera.cy) / camera.fy
  cos2 = 1.0 / (1.0 + v[:, None] ** 2 + u[None, :] ** 2)
  return 1.0 - strength + strength * cos2 * cos2


@jax.jit
def defocus_sigma(depth, fx, *, aperture, focus_distance, optical_blur):
  """`(H, W)` Gaussian σ in pixels of the lens blur at each pixel's depth.

  The thin-lens circle of confusion has diameter `c = aperture · fx · |1/focus − 1/z|` pixels;
  a uniform disc of diameter c has a per-axis σ of c/4, added in quadrature to `optical_blur`.
  Pixels without depth (0) are treated as far away.
  """
  z = jnp.where(depth > 0, depth, 1e3)
  coc = aperture * fx * jnp.abs(1.0 / focus_distance - 1.0 / z)
  return jnp.sqrt(optical_blur ** 2 + (coc / 4.0) ** 2)


def _gaussian_blur(img, sigma: float):
  """Separable Gaussian blur of `(H, W, C)` with edge padding (σ static, radius ⌈3σ⌉)."""
  if sigma <= 0:
    return img
  radius = int(np.ceil(3.0 * sigma))
  w = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
  w = (w / w.sum()).astype(np.float32)
  h, wd = img.shape[:2]
  p = jnp.pad(img, ((radius, radius), (0, 0), (0, 0)), mode="edge")
  img = sum(float(w[i]) * p[i:i + h] for i in range(2 * radius + 1))
  p = jnp.pad(img, ((0, 0), (radius, radius), (0, 0)), mode="edge")
  return sum(float(w[i]) * p[:, i:i + wd] for i in range(2 * radius + 1))


@jax.jit
def variable_blur(img, sigma):
  """Blurs each pixel of `img (H, W, C)` by its own Gaussian σ `sigma (H, W)` in pixels.

  The image is blurred at each of `BLUR_LEVELS` and every pixel linearly interpolates between
  the two levels around its σ (clipped to the largest level). Levels no pixel needs are skipped
  at run time.
  """
  img = jnp.asarray(img)
  levels = np.asarray(BLUR_LEVELS, np.float32)
  s = jnp.clip(sigma, 0.0, levels[-1])
  out = jnp.zeros_like(img)
  for i, level in enumerate(levels):
    lo = levels[i - 1] if i > 0 else level
    hi = levels[i + 1] if i + 1 < len(levels) else level
    rise = (s - lo) / (level - lo) if level > lo else jnp.ones_like(s)
    fall = (hi - s) / (hi - level) if hi > level else jnp.ones_like(s)
    weight = jnp.clip(jnp.minimum(rise, fall), 0.0, 1.0)
    weight = jnp.where((s >= lo) & (s <= hi), weight, 0.0)[..., None]
    blur = lambda x, w=weight, level=float(level): x + w * _gaussian_blur(img, level)
    out = jax.lax.cond(jnp.any(weight > 0), blur, lambda x: x, out)
  return out


def _quads(img):
  """`(H·W, 4C)`: each pixel's 2×2 neighbourhood (itself, right, below, below-right; edges
  repeated), so that one gather fetches everything a bilinear sample needs."""
  right = jnp.concatenate([img[:, 1:], img[:, -1:]], axis=1)
  below = jnp.concatenate([img[1:], img[-1:]], axis=0)
  below_right = jnp.concatenate([right[1:], right[-1:]], axis=0)
  h, w, c = img.shape
  return jnp.concatenate([img, right, below, below_right], axis=-1).reshape(h * w, 4 * c)


def _bilinear_quads(quads, height: int, width: int, v, u):
  """Samples the image behind `_quads` at float pixel coordinates `v, u (H, W)` (clamped to
  the image); returns `(H, W, C)`."""
  u = jnp.clip(u, 0.0, width - 1.0)
  v = jnp.clip(v, 0.0, height - 1.0)
  u0 = jnp.floor(u)
  v0 = jnp.floor(v)
  fu = (u - u0)[..., None]
  fv = (v - v0)[..., None]
  q = jnp.take(quads, v0.astype(jnp.int32) * width + u0.astype(jnp.int32), axis=0)
  c = quads.shape[-1] // 4
  top = q[..., :c] * (1.0 - fu) + q[..., c:2 * c] * fu
  bottom = q[..., 2 * c:3 * c] * (1.0 - fu) + q[..., 3 * c:] * fu
  return top * (1.0 - fv) + bottom * fv


def _backproject(depth, camera: Camera):
  """`(x, y, z, u_ref, v_ref)`, each `(H, W)`: camera-frame points of the pixels and their
  projections relative to the principal point."""
  h, w = depth.shape
  z = jnp.where(depth > 0, depth, 1e3)
  u = jnp.arange(w, dtype=jnp.float32)[None, :]
  v = jnp.arange(h, dtype=jnp.float32)[:, None]
  x = (u - camera.cx) / camera.fx * z
  y = (v - camera.cy) / camera.fy * z
  return x, y, z, camera.fx * x / z, camera.fy * y / z


def _tap_flow(points, camera: Camera, T):
  """`(du, dv)` `(H, W)` to one tap pose `T (4, 4)` (elementwise: a 3×3 `dot` is slow on CPU)."""
  x, y, z, u_ref, v_ref = points
  px, py, pz = x - T[0, 3], y - T[1, 3], z - T[2, 3]
  qx = px * T[0, 0] + py * T[1, 0] + pz * T[2, 0]  # R^T (p − t)
  qy = px * T[0, 1] + py * T[1, 1] + pz * T[2, 1]
  qz = jnp.maximum(px * T[0, 2] + py * T[1, 2] + pz * T[2, 2], 1e-3)
  return camera.fx * qx / qz - u_ref, camera.fy * qy / qz - v_ref


@jax.jit
def motion_flow(depth, camera: Camera, motion):
  """Per-pixel image displacement to each pose of the exposure.

  Args:
    depth: `(H, W)` z-depth (0: far away).
    camera: intrinsics.
    motion: `(K, 4, 4)` `T_cam_tap`.

  Returns:
    `(du, dv)`, each `(K, H, W) float32`: where the surface seen at a pixel appears in each tap's
    image, minus where it appears in the frame's (exactly 0 for an identity tap).
  """
  points = _backproject(depth, camera)
  motion = jnp.asarray(motion, jnp.float32)
  flows = [_tap_flow(points, camera, motion[k]) for k in range(motion.shape[0])]
  return jnp.stack([f[0] for f in flows]), jnp.stack([f[1] for f in flows])


@jax.jit
def motion_blur(img, depth, camera: Camera, motion):
  """Averages `img (H, W, C)` over the camera poses `motion (K, 4, 4)` of one exposure.

  Each pixel is sampled (bilinearly) K times along the line its flow traces, `p − flow_k`: the
  surfaces that crossed the pixel while the shutter was open. A still camera (all poses
  identity) returns `img` unchanged.
  """
  img = jnp.asarray(img)
  motion = jnp.asarray(motion, jnp.float32)
  h, w = depth.shape
  u = jnp.arange(w, dtype=jnp.float32)[None, :]
  v = jnp.arange(h, dtype=jnp.float32)[:, None]

  def blur(img):
    points = _backproject(depth, camera)
    quads = _quads(img)
    acc = jnp.zeros_like(img)
    for k in range(motion.shape[0]):  # K static; a running sum (a leading-axis mean is slow)
      du, dv = _tap_flow(points, camera, motion[k])
      acc = acc + _bilinear_quads(quads, h, w, v - dv, u - du)
    return acc / motion.shape[0]

  still = jnp.all(motion == jnp.eye(4, dtype=jnp.float32))
  return jax.lax.cond(still, lambda x: x, blur, img)


def meter_weights(height: int, width: int):
  """`(H, W) float32` centre-weighted metering window (sums to 1)."""
  y = (np.arange(height) - (height - 1) / 2.0)
  x = (np.arange(width) - (width - 1) / 2.0)
  r2 = y[:, None] ** 2 + x[None, :] ** 2
  sigma = _METER_SIGMA * np.hypot(height, width)
  w = np.exp(-0.5 * r2 / sigma ** 2)
  return (w / w.sum()).astype(np.float32)


@jax.jit
def meter(image):
  """Centre-weighted mean luma of `image (H, W, 3)` (what the AE measures)."""
  luma = image @ jnp.asarray(_LUMA, jnp.float32)
  return jnp.sum(luma * meter_weights(*image.shape[:2]))


def camera_image(key, radiance, depth, camera: Camera, state: CameraState, config: SensingConfig):
  """Turns a frame's scene radiance into the camera's colour image.

  Motion blur and defocus (optics), vignetting, exposure, shot and read noise (sensor), white
  balance and clipping (ISP), in that order.

  Args:
    key: PRNG key of the pixel noise.
    radiance: `(H, W, 3) float32` linear scene radiance (≥ 0, may exceed 1).
    depth: `(H, W) float32` exact z-depth (0: nothing hit).
    camera: intrinsics.
    state: this frame's `CameraState`.
    config: `SensingConfig` (its numbers are traced: changing them does not recompile).

  Returns:
    `(rgb, metered)`: `(H, W, 3) float32` colour in [0, 1] before 8-bit quantisation, and the
    scalar centre-weighted brightness of the noise-free image (what the AE meters).
  """
  if radiance.ndim != 3 or radiance.shape[-1] != 3 or radiance.shape[:2] != depth.shape:
    raise ValueError(f"radiance must be (H, W, 3) and depth (H, W); got {radiance.shape}, "
                     f"{depth.shape}")
  if not isinstance(state, CameraState) or np.ndim(state.motion) != 3 or np.shape(
      state.motion)[1:] != (4, 4):
    raise ValueError("state must be a CameraState with motion of shape (K, 4, 4)")
  # Two compiled pieces: the motion blur is compiled once per number of poses K, the rest once.
  img = motion_blur(radiance, depth, camera, state.motion)
  return _lens_and_sensor(key, img, depth, camera, state._replace(motion=None), config)


@jax.jit
def _lens_and_sensor(key, img, depth, camera: Camera, state: CameraState, config: SensingConfig):
  """Defocus, vignetting, exposure, noise, white balance and clipping (see `camera_image`)."""
  height, width = depth.shape
  sigma = defocus_sigma(depth, camera.fx, aperture=config.aperture,
                        focus_distance=config.focus_distance, optical_blur=config.optical_blur)
  img = variable_blur(img, sigma)
  gain = state.exposure * vignetting_gain(camera, height, width, config.vignetting)
  raw = img * gain[..., None]
  var = (config.shot_noise * state.gain * jnp.maximum(raw, 0.0)
         + jnp.square(config.read_noise * state.gain))
  noisy = raw + state.noise_scale * jnp.sqrt(var) * jax.random.normal(key, raw.shape)
  rgb = jnp.clip(noisy * state.white_balance, 0.0, 1.0)
  metered = meter(jnp.clip(raw * state.white_balance, 0.0, 1.0))
  return rgb, metered
