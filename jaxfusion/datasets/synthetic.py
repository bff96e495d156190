"""The embedded synthetic world: public entry points.

The paper's AirSim evaluation (two environments × three trajectories, 7 classes, a network
trained on different data) is replaced by procedural rooms rendered with a JAX ray caster:

* `list_sequences()` — the 2 × 3 `(env, trajectory)` pairs of the paper;
* `make_sequence(env, trajectory, ...)` — a rendered `RGBDSequence` with GT labels;
* `sample_views(domain, n, ...)` — random labelled views of many random rooms, to train a
  segmentation net on the "train" domain and meet the "test" domain at mapping time;
* `make_scene` / `scene_from_layout` / `render` — the scene and the single-frame renderer
  behind them (`changes` renders worlds that change between two passes, or drifting poses);
* `placement(env, seed)` — where a room sits in the world frame the sequences report.

Rooms are modelled in their own frame, with walls, floor and much of the furniture on whole
decimetres. A real room is not aligned with anyone's voxel grid, so `make_sequence` reports its
poses in a world frame where the room sits at `placement(env, seed)`: turned by 5–15° about the
vertical and tilted by 1–3° about each horizontal axis, and shifted by up to 0.1 m along each
axis, all drawn from the layout seed. No surface then lies on a face of a 0.1 m (or any other)
voxel grid. Rendering is unchanged (`render` takes the pose in the room's frame), and so are
the images, depths and labels; the GT voxel labels come from depth and the reported poses, so
they stay consistent.

With `realism` (the default of the sequences and views), colour goes through the camera model
of `camera_model.SensingConfig` — auto-exposure and white-balance drift, motion blur, defocus,
glossy highlights, vignetting, per-frame sensor noise — in both domains; `SensingConfig.off()`
gives the plain sensor model (blur, vignetting and noise alike in every frame). Depth keeps its
own sensor model and the labels stay exact either way.

Example:
  >>> seq = make_sequence("office", 0, num_frames=30, height=120, width=160)
  >>> frame = seq[0]; frame.depth.shape
  (120, 160)
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion.camera import Camera
from jaxfusion.datasets import appearance, camera_model, raycast, scene, sensor_noise, trajectories
from jaxfusion.datasets.classes import BACKGROUND, CLASS_NAMES
from jaxfusion.datasets.primitives import Primitives, rot_x, rot_y, rot_z
from jaxfusion.datasets.camera_model import CameraState, SensingConfig
from jaxfusion.datasets.sequence import RGBDFrame, RGBDSequence

ENVIRONMENTS = scene.ENVIRONMENTS
NUM_TRAJECTORIES = 3
# Horizontal field of view of the synthetic camera: fx = FOCAL_FACTOR · W (≈ 79°).
FOCAL_FACTOR = 0.6
# Screen tiles of the ray caster: each tile × tile block is cast against its own candidates.
TILE = 16
# Coarse padding of the per-kind tables and generous per-tile list lengths for random views, so
# that rendering many random rooms compiles only a handful of shapes.
VIEW_PACK_STEP = 256
VIEW_TILE_SIZES = (32, 16, 16, 8)


class SyntheticScene(NamedTuple):
  """A room in one appearance domain.

  Attributes:
    layout: the domain-independent `scene.Layout`.
    primitives: `Primitives` table (host arrays).
    lighting: `appearance.Lighting`.
    domain: "train" or "test".
    shift: the domain shift it was built with.
  """
  layout: scene.Layout
  primitives: Primitives
  lighting: appearance.Lighting
  domain: str
  shift: float


def list_sequences() -> list:
  """The paper's six sequences: `[(env, trajectory)]` for 2 environments × 3 trajectories."""
  return [(env, t) for env in ENVIRONMENTS for t in range(NUM_TRAJECTORIES)]


def placement(env: str, seed: int = 0) -> np.ndarray:
  """Where the room of `(env, seed)` sits in the world frame of its sequences.

  A rigid transform drawn from the layout seed: a turn of 5–15° (either sign) about the
  vertical, tilts of 1–3° (either sign) about the two horizontal axes and a shift uniform in
  [0, 0.1) m along each axis, so that the room's surfaces lie on no voxel grid.

  Args:
    env: "office" or "house".
    seed: layout seed.

  Returns:
    `(4, 4) float64` `T_world_room`.
  """
  if env not in ENVIRONMENTS:
    raise ValueError(f"env must be one of {ENVIRONMENTS}; got {env!r}")
  rng = np.random.default_rng([int(seed), ENVIRONMENTS.index(env), 6262])
  signs = rng.choice([-1.0, 1.0], size=3)
  yaw, pitch, roll = np.radians(signs * rng.uniform([5.0, 1.0, 1.0], [15.0, 3.0, 3.0]))
  T = np.eye(4)
  T[:3, :3] = rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)
  T[:3, 3] = rng.uniform(0.0, 0.1, size=3)
  return T


def default_camera(height: int, width: int) -> Camera:
  """The synthetic pinhole camera for an image of `height × width` pixels."""
  f = FOCAL_FACTOR * width
  return Camera(f, f, (width - 1) / 2.0, (height - 1) / 2.0)


def make_scene(env: str, *, seed: int = 0, domain: str = "test", shift: float = 1.0
               ) -> SyntheticScene:
  """Builds a room: layout from `(env, seed)`, appearance from `(domain, shift)`.

  Args:
    env: "office" or "house".
    seed: layout seed.
    domain: "train" or "test".
    shift: strength of the test domain's difference from train, in [0, 1].

  Returns:
    A `SyntheticScene`.
  """
  return scene_from_layout(scene.make_layout(env, seed), domain=domain, shift=shift)


def scene_from_layout(layout: scene.Layout, *, domain: str = "test", shift: float = 1.0
                      ) -> SyntheticScene:
  """A given layout (e.g. `changes.changed_layout`'s) in an appearance domain (`make_scene`)."""
  s = appearance.domain_shift(domain, shift)
  prims = scene.build_primitives(layout, s)
  light = appearance.lighting(layout.room, layout.light_u, s)
  return SyntheticScene(layout, prims, light, domain, float(shift))


@jax.jit
def _shade(packed: raycast.PackedScene, hits: raycast.Hits, light: appearance.Lighting):
  p = packed.prims
  g = jnp.maximum(hits.prim, 0).reshape(-1)
  albedo = appearance.texture(hits.p_local.reshape(-1, 3), p.texture[g], p.texture_scale[g],
                              p.color[g], p.color2[g])
  rgb = appearance.shade(albedo, hits.normal.reshape(-1, 3), hits.p_world.reshape(-1, 3),
                         hits.view_dir.reshape(-1, 3), p.emission[g], light)
  rgb = jnp.where((hits.prim.reshape(-1) >= 0)[:, None], rgb, 0.0)
  return rgb.reshape(hits.normal.shape)


@jax.jit
def _radiance(packed: raycast.PackedScene, hits: raycast.Hits, light: appearance.Lighting,
              origin, fx, config: SensingConfig):
  """`(H, W, 3)` unclipped scene radiance with the sensing's texture filter and glossy
  highlights (`origin (3,)`: the camera centre, `fx`: focal length in pixels)."""
  p = packed.prims
  g = jnp.maximum(hits.prim, 0).reshape(-1)
  normal, p_world = hits.normal.reshape(-1, 3), hits.p_world.reshape(-1, 3)
  view_dir = hits.view_dir.reshape(-1, 3)
  footprint = camera_model.pixel_footprint(
      jnp.linalg.norm(p_world - origin, axis=-1), jnp.abs(jnp.sum(normal * view_dir, -1)), fx,
      config.texture_filter)
  albedo = appearance.texture(hits.p_local.reshape(-1, 3), p.texture[g], p.texture_scale[g],
                              p.color[g], p.color2[g], footprint=footprint)
  rgb = appearance.shade(albedo, normal, p_world, view_dir, p.emission[g], light, clip=False)
  rgb = rgb + light.exposure * camera_model.glossy_highlight(
      normal, p_world, view_dir, p.gloss[g], light.lamp_pos, light.lamp_color, light.sun_dir,
      light.sun_color, strength=config.gloss, shininess=config.shininess)
  rgb = jnp.where((hits.prim.reshape(-1) >= 0)[:, None], rgb, 0.0)
  return rgb.reshape(hits.normal.shape)


def _scene_radiance(world: SyntheticScene, packed, hits, T, camera: Camera,
                    config: SensingConfig):
  return _radiance(packed, hits, world.lighting, np.asarray(T, np.float32)[:3, 3],
                   np.float32(camera.fx), _traced(config))


def _traced(config: SensingConfig) -> SensingConfig:
  """The config with every field as a float32 array (one compilation for all values)."""
  return SensingConfig(*(np.float32(x) for x in config))


def _check_sensing(sensing) -> SensingConfig:
  if sensing is None:
    return SensingConfig()
  if not isinstance(sensing, SensingConfig):
    raise TypeError(f"sensing must be a SensingConfig or None; got {type(sensing).__name__}")
  return sensing.validate()


def _cast(synthetic_scene: SyntheticScene, T, camera: Camera, height: int, width: int,
          tile_sizes, pack_step: int, candidates=None):
  packed = raycast.pack(synthetic_scene.primitives, step=pack_step)
  tiles = raycast.tile_lists(packed, T, camera, height=height, width=width, tile=TILE,
                             min_sizes=tile_sizes, candidates=candidates)
  return packed, raycast.cast(packed, T, camera, height=height, width=width, tiles=tiles,
                              tile=TILE)


def _converged_exposure(radiance, config: SensingConfig, bias: float = 0.0) -> float:
  """The exposure a settled AE picks for a frame (set-point `ae_target · e^bias`)."""
  metered = float(camera_model.meter(radiance))
  exposure = config.ae_target * np.exp(bias) / max(metered, 1e-4)
  return float(np.clip(exposure, config.exposure_min, config.exposure_max))


def _to_uint8(rgb) -> np.ndarray:
  return np.asarray(jnp.round(rgb * 255.0)).astype(np.uint8)


def render(synthetic_scene: SyntheticScene, T_world_cam, camera: Camera, *, height: int,
           width: int, realism: bool = False, key=None, tile_sizes=(0, 0, 0, 0),
           pack_step: int = 64, sensing: SensingConfig = None,
           state: CameraState = None, candidates=None) -> RGBDFrame:
  """Renders one frame of a synthetic scene.

  Args:
    synthetic_scene: output of `make_scene`.
    T_world_cam: `(4, 4)` camera-to-room pose, in the room's own frame (a sequence reports
      `placement(env, seed) @ T_world_cam`).
    camera: intrinsics.
    height: image rows H.
    width: image columns W.
    realism: add sensor depth noise/holes and pass colour through the camera model (labels
      stay exact). False gives the exact depth and the clean, fixed-exposure colour.
    key: PRNG key for the realism noise (default `PRNGKey(0)`).
    tile_sizes: lower bounds of the per-tile candidate list lengths (see
      `raycast.tile_lists`); give the maximum over a trajectory to compile once for all
      of its frames.
    pack_step: the per-kind primitive tables are padded to a multiple of this (coarser
      padding: fewer distinct shapes across scenes, hence fewer compilations).
    sensing: the camera model used with `realism` (default `SensingConfig()`;
      `SensingConfig.off()`: the plain blur, vignetting and noise of
      `sensor_noise.noisy_image`).
    state: this frame's `camera_model.CameraState` (exposure, white balance, noise level, motion
      during the exposure); default: a still camera whose auto-exposure has settled on this
      frame, neutral white balance, nominal noise. Sequences pass the states of their camera
      path (see `make_sequence`).
    candidates: optional `(P,) bool`: the primitives that may be hit (`raycast.tile_lists`;
      None: all). `floor` leaves out those beyond its sensor range.

  Returns:
    `RGBDFrame` with `rgb (H, W, 3) uint8`, `depth (H, W) float32`, `labels`/`instances`
    `(H, W) int32`.
  """
  config = _check_sensing(sensing)
  T = np.asarray(T_world_cam, np.float32)
  packed, hits = _cast(synthetic_scene, T, camera, height, width, tile_sizes, pack_step,
                       candidates)
  frame, _ = _finish(synthetic_scene, packed, hits, T, camera, realism=realism, key=key,
                     config=config, state=state)
  return frame


def _finish(synthetic_scene: SyntheticScene, packed, hits, T, camera: Camera, *, realism: bool,
            key, config: SensingConfig, state):
  """Colour and depth of a cast frame; returns `(RGBDFrame, metered brightness or None)`."""
  depth = hits.depth
  metered = None
  if realism and config.enabled:
    key = jax.random.PRNGKey(0) if key is None else key
    k_depth, k_image = jax.random.split(key)
    depth = sensor_noise.noisy_depth(k_depth, depth, hits.normal, hits.view_dir)
    radiance = _scene_radiance(synthetic_scene, packed, hits, T, camera, config)
    if state is None:
      state = camera_model.still_state(_converged_exposure(radiance, config))
    rgb, metered = camera_model.camera_image(k_image, radiance, hits.depth, camera, state,
                                             _traced(config))
    metered = float(metered)
  else:
    rgb = _shade(packed, hits, synthetic_scene.lighting)
    if realism:
      key = jax.random.PRNGKey(0) if key is None else key
      k_depth, k_image = jax.random.split(key)
      depth = sensor_noise.noisy_depth(k_depth, depth, hits.normal, hits.view_dir)
      rgb = sensor_noise.noisy_image(k_image, rgb)
  frame = RGBDFrame(rgb=_to_uint8(rgb), depth=np.asarray(depth, np.float32), T_world_cam=T,
                    camera=camera, labels=np.asarray(hits.label, np.int32),
                    instances=np.asarray(hits.instance, np.int32))
  return frame, metered


def trajectory_tile_sizes(synthetic_scene: SyntheticScene, poses, camera: Camera, *,
                          height: int, width: int) -> tuple:
  """The largest per-tile candidate list lengths over a set of poses (for `render`)."""
  packed = raycast.pack(synthetic_scene.primitives, step=64)
  sizes = [raycast.list_sizes(raycast.tile_lists(packed, T, camera, height=height, width=width,
                                                 tile=TILE)) for T in poses]
  return tuple(int(x) for x in np.max(np.array(sizes).reshape(-1, 4), axis=0))


def make_sequence(env: str, trajectory: int, *, domain: str = "test", num_frames: int = 60,
                  height: int = 120, width: int = 160, seed: int = 0, shift: float = 1.0,
                  realism: bool = True, sensing: SensingConfig = None) -> RGBDSequence:
  """Renders one of the paper-style sequences.

  With `realism`, the camera model runs along the trajectory: the frames lie
  `sensing.frame_interval` seconds apart (the path walked at `sensing.speed`), the
  auto-exposure meters each frame and adapts the next one with its lag, exposure and white
  balance drift, motion blur follows the velocity between consecutive poses (the first frame
  uses that towards the second), and the noise level changes from frame to frame. The
  per-frame camera settings are recorded in `info["camera_states"]`.

  Args:
    env: "office" or "house".
    trajectory: 0 (walk along the walls), 1 (orbit), 2 (sweep across the room).
    domain: "train" or "test" appearance.
    num_frames: T frames along the whole trajectory.
    height: image rows H.
    width: image columns W.
    seed: layout seed; the furniture, the path and the room's `placement` depend on
      `(env, seed)` only.
    shift: strength of the "test" domain gap in [0, 1].
    realism: sensor noise on depth and the camera model on colour (GT labels are always exact).
    sensing: the camera model (default `SensingConfig()`; `SensingConfig.off()` for the plain
      per-frame-identical sensor model).

  Returns:
    An `RGBDSequence` named `f"{env}_{trajectory}_{domain}"` with `CLASS_NAMES` labels and
    instance ids. Its poses are in the world frame, where the room sits at
    `placement(env, seed)` (also in `info["T_world_room"]`); `render` takes room-frame poses.
  """
  if trajectory not in range(NUM_TRAJECTORIES):
    raise ValueError(f"trajectory must be 0, 1 or 2; got {trajectory}")
  if height < 1 or width < 1:
    raise ValueError(f"image size must be positive; got {height}x{width}")
  config = _check_sensing(sensing)
  world = make_scene(env, seed=seed, domain=domain, shift=shift)
  camera = default_camera(height, width)
  poses = trajectories.trajectory(world.layout.room, trajectory, num_frames)
  keys = jax.random.split(jax.random.PRNGKey(seed * 7 + trajectory), num_frames)
  info = _sequence_info(world, trajectory, seed=seed, realism=realism)
  # The camera's drift depends on the sequence, not on the domain: both see the same camera.
  rng = np.random.default_rng([seed, trajectory, ENVIRONMENTS.index(env), 5151])
  frames, states = _render_path(world, poses, keys, camera, config, realism=realism,
                                height=height, width=width, rng=rng)
  if states is not None:
    info["camera_states"], info["sensing"] = states, config.as_dict()
  return _stack_frames(f"{env}_{trajectory}_{domain}", camera, frames,
                       np.einsum("ij,tjk->tik", placement(env, seed), poses), info)


def _sequence_info(world: SyntheticScene, trajectory: int, *, seed: int, realism: bool) -> dict:
  """The provenance `info` of a sequence through `world` (before any camera states)."""
  env = world.layout.env
  return {"source": "synthetic", "env": env, "trajectory": int(trajectory),
          "trajectory_name": trajectories.TRAJECTORY_NAMES[trajectory], "domain": world.domain,
          "seed": int(seed), "shift": float(world.shift), "realism": bool(realism),
          "room_size": [float(x) for x in world.layout.room],
          "T_world_room": placement(env, seed).tolist()}


def _render_path(world: SyntheticScene, poses, keys, camera: Camera, config: SensingConfig, *,
                 realism: bool, height: int, width: int, rng) -> tuple:
  """The frames of `world` seen from room-frame `poses (T, 4, 4)` with PRNG `keys (T, 2)`;
  returns `(frames, camera_states dict or None)` (the camera model's draws come from `rng`)."""
  sizes = trajectory_tile_sizes(world, poses, camera, height=height, width=width)
  if realism and config.enabled:
    return _sensed_frames(world, poses, keys, camera, sizes, config, height=height, width=width,
                          rng=rng)
  return [render(world, T, camera, height=height, width=width, realism=realism, key=k,
                 tile_sizes=sizes, sensing=config) for T, k in zip(poses, keys)], None


def _stack_frames(name: str, camera: Camera, frames, T_world_cam, info: dict) -> RGBDSequence:
  """An `RGBDSequence` of rendered frames with world-frame poses `T_world_cam (T, 4, 4)`."""
  return RGBDSequence(
      name=name, class_names=CLASS_NAMES, camera=camera,
      rgb=np.stack([f.rgb for f in frames]), depth=np.stack([f.depth for f in frames]),
      T_world_cam=np.asarray(T_world_cam).astype(np.float32),
      labels=np.stack([f.labels for f in frames]),
      instances=np.stack([f.instances for f in frames]), info=info)


def _sensed_frames(world: SyntheticScene, poses, keys, camera: Camera, sizes,
                   config: SensingConfig, *, height: int, width: int, rng) -> tuple:
  """Renders a trajectory through the camera model; returns `(frames, camera_states dict)`."""
  num_frames = len(poses)
  dt = camera_model.frame_interval(poses, config.speed)
  bias = camera_model.ou_process(rng, num_frames, dt, config.exposure_drift,
                                 config.drift_time_constant)[:, 0]
  log_wb = np.clip(camera_model.ou_process(rng, num_frames, dt, config.wb_drift,
                                           config.drift_time_constant, dims=2),
                   -config.wb_range, config.wb_range)
  noise_scale = np.exp(config.noise_jitter * rng.normal(size=num_frames))
  record = {"frame_interval_s": dt, "exposure": [], "exposure_time_s": [], "gain": [],
            "white_balance": [], "noise_scale": [], "metered": []}
  frames = []
  log_exposure = None
  for t, (T, k) in enumerate(zip(poses, keys)):
    T = np.asarray(T, np.float32)
    packed, hits = _cast(world, T, camera, height, width, sizes, 64)
    if log_exposure is None:  # the camera was running before the first frame: AE settled
      radiance = _scene_radiance(world, packed, hits, T, camera, config)
      log_exposure = float(np.log(_converged_exposure(radiance, config, bias[0])))
    exposure = float(np.exp(log_exposure))
    exposure_time, gain = camera_model.split_exposure(exposure, config)
    if num_frames > 1:
      other = poses[t - 1] if t > 0 else poses[1]
      v, w = camera_model.velocity(other, T, dt)
      if t == 0:
        v, w = -v, -w
      motion = camera_model.exposure_motion(v, w, exposure_time, hits.depth, camera)
    else:
      motion = camera_model.still_state().motion
    wb = np.array([np.exp(log_wb[t, 0]), 1.0, np.exp(log_wb[t, 1])], np.float32)
    state = CameraState(np.float32(exposure), np.float32(gain), wb, np.float32(noise_scale[t]),
                        motion)
    frame, metered = _finish(world, packed, hits, T, camera, realism=True, key=k, config=config,
                             state=state)
    frames.append(frame)
    log_exposure = camera_model.ae_step(log_exposure, metered,
                                        config.ae_target * np.exp(bias[t]), dt=dt, config=config)
    for name, value in (("exposure", exposure), ("exposure_time_s", exposure_time),
                        ("gain", gain), ("noise_scale", float(noise_scale[t])),
                        ("metered", metered)):
      record[name].append(round(float(value), 6))
    record["white_balance"].append([round(float(x), 6) for x in wb])
  return frames, record


def sample_views(domain: str, num_images: int, *, height: int, width: int, seed: int = 0,
                 shift: float = 1.0, views_per_scene: int = 8,
                 sensing: SensingConfig = None) -> tuple:
  """Random labelled views of many random rooms of both environment styles.

  The rooms use layout seeds disjoint from those of `make_sequence` (which uses small seeds),
  so a net trained on these views has never seen the evaluation rooms. Colour goes through the
  same camera model as the sequences; as the views are independent, each draws its camera
  settings from the model's stationary spread: exposure from a settled AE with a drifted
  set-point, white balance and noise level from their drift distributions, and motion blur
  from a random hand-held velocity (`camera_model.random_velocity`).

  Args:
    domain: "train" or "test" appearance.
    num_images: n views.
    height: image rows H.
    width: image columns W.
    seed: seed of the whole draw.
    shift: strength of the "test" domain gap in [0, 1].
    views_per_scene: views rendered from each random room.
    sensing: the camera model (default `SensingConfig()`; `SensingConfig.off()`: the plain
      blur and noise of `sensor_noise.noisy_image`). The rooms and poses do not depend on it.

  Returns:
    `(rgb (n, H, W, 3) uint8, labels (n, H, W) int32)`; colour has the camera's effects,
    labels are exact.
  """
  if num_images < 0:
    raise ValueError(f"num_images must be ≥ 0; got {num_images}")
  config = _check_sensing(sensing)
  camera = default_camera(height, width)
  rng = np.random.default_rng([int(seed), 424242])
  sense_rng = np.random.default_rng([int(seed), 424243])  # camera draws: poses stay the same
  rgbs = np.zeros((num_images, height, width, 3), np.uint8)
  labels = np.zeros((num_images, height, width), np.int32)
  world = None
  for i in range(num_images):
    if i % views_per_scene == 0:
      scene_index = i // views_per_scene
      env = ENVIRONMENTS[(scene_index + int(seed)) % 2]
      world = make_scene(env, seed=1_000_000 + int(seed) * 10_007 + scene_index, domain=domain,
                         shift=shift)
      objects = [pl for pl in world.layout.placements if pl.label != BACKGROUND]
    target = None
    if objects and rng.uniform() < 0.8:
      pl = objects[int(rng.integers(len(objects)))]
      target = pl.position + np.array([0.0, 0.0, 0.3])
    T = trajectories.random_view(rng, world.layout.room, target=target)
    packed, hits = _cast(world, np.asarray(T, np.float32), camera, height, width,
                         VIEW_TILE_SIZES, VIEW_PACK_STEP)
    key = jax.random.PRNGKey(int(rng.integers(2**31)))
    if config.enabled:
      radiance = _scene_radiance(world, packed, hits, T, camera, config)
      state = _random_state(sense_rng, radiance, hits.depth, T, camera, config)
      rgb, _ = camera_model.camera_image(key, radiance, hits.depth, camera, state,
                                         _traced(config))
    else:
      clean = _to_uint8(_shade(packed, hits, world.lighting))
      rgb = sensor_noise.noisy_image(key, jnp.asarray(clean, jnp.float32) / 255.0)
    rgbs[i] = _to_uint8(rgb)
    labels[i] = np.asarray(hits.label, np.int32)
  return rgbs, labels


def _random_state(rng: np.random.Generator, radiance, depth, T_world_cam, camera: Camera,
                  config: SensingConfig) -> CameraState:
  """Camera settings of an independent view, drawn from the camera model's stationary spread."""
  bias = rng.normal(0.0, config.exposure_drift)
  exposure = _converged_exposure(radiance, config, bias)
  exposure_time, gain = camera_model.split_exposure(exposure, config)
  log_wb = np.clip(rng.normal(0.0, config.wb_drift, 2), -config.wb_range, config.wb_range)
  v, w = camera_model.random_velocity(rng, T_world_cam, config)
  return CameraState(np.float32(exposure), np.float32(gain),
                     np.array([np.exp(log_wb[0]), 1.0, np.exp(log_wb[1])], np.float32),
                     np.float32(np.exp(config.noise_jitter * rng.normal())),
                     camera_model.exposure_motion(v, w, exposure_time, depth, camera))
