"""The embedded synthetic world: public entry points.

The paper's AirSim evaluation (two environments × three trajectories, 7 classes, a network
trained on different data) is replaced by procedural rooms rendered with a JAX ray caster:

* `list_sequences()` — the 2 × 3 `(env, trajectory)` pairs of the paper;
* `make_sequence(env, trajectory, ...)` — a rendered `RGBDSequence` with GT labels;
* `sample_views(domain, n, ...)` — random labelled views of many random rooms, to train a
  segmentation net on the "train" domain and meet the "test" domain at mapping time;
* `make_scene` / `render` — the scene and the single-frame renderer behind them.

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
from jaxfusion.datasets import appearance, raycast, scene, sensor, trajectories
from jaxfusion.datasets.classes import BACKGROUND, CLASS_NAMES
from jaxfusion.datasets.primitives import Primitives
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
  s = appearance.domain_shift(domain, shift)
  layout = scene.make_layout(env, seed)
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


def render(synthetic_scene: SyntheticScene, T_world_cam, camera: Camera, *, height: int,
           width: int, realism: bool = False, key=None, tile_sizes=(0, 0, 0, 0),
           pack_step: int = 64) -> RGBDFrame:
  """Renders one frame of a synthetic scene.

  Args:
    synthetic_scene: output of `make_scene`.
    T_world_cam: `(4, 4)` camera-to-world pose.
    camera: intrinsics.
    height: image rows H.
    width: image columns W.
    realism: add sensor depth noise/holes and image blur/noise (labels stay exact).
    key: PRNG key for the realism noise (default `PRNGKey(0)`).
    tile_sizes: lower bounds of the per-tile candidate list lengths (see
      `raycast.tile_lists`); give the maximum over a trajectory to compile once for all
      of its frames.
    pack_step: the per-kind primitive tables are padded to a multiple of this (coarser
      padding: fewer distinct shapes across scenes, hence fewer compilations).

  Returns:
    `RGBDFrame` with `rgb (H, W, 3) uint8`, `depth (H, W) float32`, `labels`/`instances`
    `(H, W) int32`.
  """
  packed = raycast.pack(synthetic_scene.primitives, step=pack_step)
  T = np.asarray(T_world_cam, np.float32)
  tiles = raycast.tile_lists(packed, T, camera, height=height, width=width, tile=TILE,
                             min_sizes=tile_sizes)
  hits = raycast.cast(packed, T, camera, height=height, width=width, tiles=tiles, tile=TILE)
  rgb = _shade(packed, hits, synthetic_scene.lighting)
  depth = hits.depth
  if realism:
    key = jax.random.PRNGKey(0) if key is None else key
    k_depth, k_image = jax.random.split(key)
    depth = sensor.noisy_depth(k_depth, depth, hits.normal, hits.view_dir)
    rgb = sensor.noisy_image(k_image, rgb)
  rgb8 = np.asarray(jnp.round(rgb * 255.0)).astype(np.uint8)
  return RGBDFrame(rgb=rgb8, depth=np.asarray(depth, np.float32), T_world_cam=T, camera=camera,
                   labels=np.asarray(hits.label, np.int32),
                   instances=np.asarray(hits.instance, np.int32))


def trajectory_tile_sizes(synthetic_scene: SyntheticScene, poses, camera: Camera, *,
                          height: int, width: int) -> tuple:
  """The largest per-tile candidate list lengths over a set of poses (for `render`)."""
  packed = raycast.pack(synthetic_scene.primitives, step=64)
  sizes = [raycast.list_sizes(raycast.tile_lists(packed, T, camera, height=height, width=width,
                                                 tile=TILE)) for T in poses]
  return tuple(int(x) for x in np.max(np.array(sizes).reshape(-1, 4), axis=0))


def make_sequence(env: str, trajectory: int, *, domain: str = "test", num_frames: int = 60,
                  height: int = 120, width: int = 160, seed: int = 0, shift: float = 1.0,
                  realism: bool = True) -> RGBDSequence:
  """Renders one of the paper-style sequences.

  Args:
    env: "office" or "house".
    trajectory: 0 (walk along the walls), 1 (orbit), 2 (sweep across the room).
    domain: "train" or "test" appearance.
    num_frames: T frames along the whole trajectory.
    height: image rows H.
    width: image columns W.
    seed: layout seed; the furniture and the path depend on `(env, seed)` only.
    shift: strength of the "test" domain gap in [0, 1].
    realism: sensor noise on depth and colour (GT labels are always exact).

  Returns:
    An `RGBDSequence` named `f"{env}_{trajectory}_{domain}"` with `CLASS_NAMES` labels and
    instance ids.
  """
  if trajectory not in range(NUM_TRAJECTORIES):
    raise ValueError(f"trajectory must be 0, 1 or 2; got {trajectory}")
  if height < 1 or width < 1:
    raise ValueError(f"image size must be positive; got {height}x{width}")
  world = make_scene(env, seed=seed, domain=domain, shift=shift)
  camera = default_camera(height, width)
  poses = trajectories.trajectory(world.layout.room, trajectory, num_frames)
  keys = jax.random.split(jax.random.PRNGKey(seed * 7 + trajectory), num_frames)
  sizes = trajectory_tile_sizes(world, poses, camera, height=height, width=width)
  frames = [render(world, T, camera, height=height, width=width, realism=realism, key=k,
                   tile_sizes=sizes) for T, k in zip(poses, keys)]
  return RGBDSequence(
      name=f"{env}_{trajectory}_{domain}", class_names=CLASS_NAMES, camera=camera,
      rgb=np.stack([f.rgb for f in frames]), depth=np.stack([f.depth for f in frames]),
      T_world_cam=poses, labels=np.stack([f.labels for f in frames]),
      instances=np.stack([f.instances for f in frames]),
      info={"source": "synthetic", "env": env, "trajectory": int(trajectory),
            "trajectory_name": trajectories.TRAJECTORY_NAMES[trajectory], "domain": domain,
            "seed": int(seed), "shift": float(shift), "realism": bool(realism),
            "room_size": [float(x) for x in world.layout.room]})


def sample_views(domain: str, num_images: int, *, height: int, width: int, seed: int = 0,
                 shift: float = 1.0, views_per_scene: int = 8) -> tuple:
  """Random labelled views of many random rooms of both environment styles.

  The rooms use layout seeds disjoint from those of `make_sequence` (which uses small seeds),
  so a net trained on these views has never seen the evaluation rooms.

  Args:
    domain: "train" or "test" appearance.
    num_images: n views.
    height: image rows H.
    width: image columns W.
    seed: seed of the whole draw.
    shift: strength of the "test" domain gap in [0, 1].
    views_per_scene: views rendered from each random room.

  Returns:
    `(rgb (n, H, W, 3) uint8, labels (n, H, W) int32)`; colour has sensor blur and noise,
    labels are exact.
  """
  if num_images < 0:
    raise ValueError(f"num_images must be ≥ 0; got {num_images}")
  camera = default_camera(height, width)
  rng = np.random.default_rng([int(seed), 424242])
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
    frame = render(world, T, camera, height=height, width=width, realism=False,
                   tile_sizes=VIEW_TILE_SIZES, pack_step=VIEW_PACK_STEP)
    rgb = sensor.noisy_image(jax.random.PRNGKey(int(rng.integers(2**31))),
                             jnp.asarray(frame.rgb, jnp.float32) / 255.0)
    rgbs[i] = np.asarray(jnp.round(rgb * 255.0)).astype(np.uint8)
    labels[i] = frame.labels
  return rgbs, labels
