"""The true surface of an embedded-world sequence: points on the primitives' exact surfaces,
with their class, where the sequence's cameras see them.

The primitives are ray cast analytically (`raycast.cast`, no sensor model: no noise, holes,
blur or quantisation) from every pose of the sequence at `upsample` times its resolution; each
hit lies on a primitive's surface (up to float32) and carries that primitive's class. The hits
are thinned to one per cell of a `spacing` grid (the first in frame and pixel order), which
samples the seen surface about evenly — one point per `spacing²` of surface facing the grid,
up to √3 more on oblique surfaces — whatever the viewing distance. Surface that no camera of
the sequence sees is not part of it: a mesh cannot be asked to complete what was never
observed (NICE-SLAM and Atlas cull their GT meshes to the frustums in the same spirit).

Shape legend: G surface points, T frames.
"""

import functools

import jax
import numpy as np

from jaxfusion.camera import Camera
from jaxfusion.datasets import raycast
from jaxfusion.datasets import synthetic

DEFAULT_SPACING = 0.01
DEFAULT_UPSAMPLE = 2


@functools.partial(jax.jit, static_argnames=("height", "width"))
def _hits(packed, T_world_cam, camera: Camera, *, height: int, width: int):
  hits = raycast.cast(packed, T_world_cam, camera, height=height, width=width)
  return hits.p_world, hits.prim, hits.label


def upsampled_camera(camera: Camera, factor: int) -> Camera:
  """The intrinsics of the same camera with `factor`² pixels per pixel (pixel centres at
  integer coordinates, as everywhere in jaxfusion)."""
  return Camera(camera.fx * factor, camera.fy * factor, (camera.cx + 0.5) * factor - 0.5,
                (camera.cy + 0.5) * factor - 0.5)


def seen_surface(world: synthetic.SyntheticScene, T_world_cam, camera: Camera,
                 image_size, *, T_world_room=None, spacing: float = DEFAULT_SPACING,
                 upsample: int = DEFAULT_UPSAMPLE) -> dict:
  """Even samples of the primitives' surface that the cameras see.

  Args:
    world: the sequence's scene (`synthetic.make_scene` with its layout seed and shift; only
      its `primitives`, in the room frame, are used).
    T_world_cam: `(T, 4, 4)` camera-to-world poses of the sequence.
    T_world_room: `(4, 4)` where the room sits in the world (`synthetic.placement`; the
      sequence's `info["T_world_room"]`); None: the identity.
    camera: the sequence's intrinsics.
    image_size: `(H, W)` of the sequence.
    spacing: thinning grid edge in metres (> 0).
    upsample: rays per pixel along each image axis (≥ 1).

  Returns:
    dict with `points (G, 3) float64` (world), `labels (G,) int32` (class of the primitive
    hit) and `primitive (G,) int32` (its row in `world.primitives`).
  """
  poses = np.asarray(T_world_cam, np.float32)
  if poses.ndim != 3 or poses.shape[1:] != (4, 4) or not np.all(np.isfinite(poses)):
    raise ValueError(f"T_world_cam must be finite (T, 4, 4); got shape {poses.shape}")
  if not spacing > 0:
    raise ValueError(f"spacing must be positive; got {spacing}")
  if int(upsample) != upsample or upsample < 1:
    raise ValueError(f"upsample must be a positive integer; got {upsample}")
  room = np.eye(4) if T_world_room is None else np.asarray(T_world_room, np.float64)
  if room.shape != (4, 4) or not np.all(np.isfinite(room)):
    raise ValueError(f"T_world_room must be a finite (4, 4) matrix; got shape {room.shape}")
  room_poses = np.einsum("ij,tjk->tik", np.linalg.inv(room), poses).astype(np.float32)
  height, width = (int(x) * int(upsample) for x in image_size)
  cam = upsampled_camera(camera, int(upsample))
  packed = raycast.pack(world.primitives)
  points, labels, prims = [], [], []
  for T in room_poses:
    p, prim, label = (np.asarray(x) for x in _hits(packed, T, cam, height=height, width=width))
    hit = prim.reshape(-1) >= 0
    points.append(p.reshape(-1, 3)[hit].astype(np.float64) @ room[:3, :3].T + room[:3, 3])
    labels.append(label.reshape(-1)[hit])
    prims.append(prim.reshape(-1)[hit])
  points = np.concatenate(points) if points else np.zeros((0, 3))
  labels = np.concatenate(labels).astype(np.int32) if labels else np.zeros(0, np.int32)
  prims = np.concatenate(prims).astype(np.int32) if prims else np.zeros(0, np.int32)
  _, first = np.unique(np.floor(points / spacing).astype(np.int64), axis=0, return_index=True)
  first = np.sort(first)
  return {"points": points[first], "labels": labels[first], "primitive": prims[first]}


def sequence_surface(env: str, layout_seed: int, shift: float, sequence, *,
                     domain: str = "test", spacing: float = DEFAULT_SPACING,
                     upsample: int = DEFAULT_UPSAMPLE) -> dict:
  """`seen_surface` of an embedded sequence rendered by `synthetic.make_sequence(env, …,
  seed=layout_seed, shift=shift, domain=domain)` (its poses, camera and image size; the room
  placed at `synthetic.placement(env, layout_seed)`, as the sequence's poses are)."""
  world = synthetic.make_scene(env, seed=layout_seed, domain=domain, shift=shift)
  return seen_surface(world, sequence.T_world_cam, sequence.camera, sequence.image_size,
                      T_world_room=synthetic.placement(env, layout_seed), spacing=spacing,
                      upsample=upsample)
