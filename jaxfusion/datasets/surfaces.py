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


MESH_SUFFIX = "_vh_clean_2.labels.ply"


def labelled_mesh_path(folder: str):
  """The labelled GT mesh of a ScanNet scene folder (`<scene>_vh_clean_2.labels.ply`, or any
  `*_vh_clean_2.labels.ply` in it), or None."""
  import glob  # pylint: disable=import-outside-toplevel
  import os  # pylint: disable=import-outside-toplevel
  own = os.path.join(folder, os.path.basename(os.path.normpath(folder)) + MESH_SUFFIX)
  if os.path.isfile(own):
    return own
  found = sorted(glob.glob(os.path.join(folder, "*" + MESH_SUFFIX)))
  return found[0] if found else None


def seen_points(points: np.ndarray, sequence, *, tolerance: float = 0.05) -> np.ndarray:
  """`(G,) bool`: which world points some frame of the sequence sees, i.e. projects inside the
  image in front of the camera within `tolerance` metres of the measured depth there (a
  point behind the measured surface is occluded; one with no depth is not seen)."""
  points = np.asarray(points, np.float64)
  seen = np.zeros(len(points), bool)
  cam = sequence.camera
  h, w = sequence.image_size
  for depth, T in zip(sequence.depth, sequence.T_world_cam):
    T = np.asarray(T, np.float64)
    p = (points - T[:3, 3]) @ T[:3, :3]                    # world → camera: R^T (p − t)
    z = p[:, 2]
    front = z > 1e-6
    u = np.full(len(p), -1, np.int64)
    v = np.full(len(p), -1, np.int64)
    u[front] = np.round(cam.fx * p[front, 0] / z[front] + cam.cx).astype(np.int64)
    v[front] = np.round(cam.fy * p[front, 1] / z[front] + cam.cy).astype(np.int64)
    inside = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    d = np.zeros(len(p))
    d[inside] = depth[v[inside], u[inside]]
    seen |= inside & (d > 0) & (np.abs(d - z) <= tolerance)
  return seen


def mesh_surface(path: str, sequence, *, label_space: str = "scannet12",
                 spacing: float = DEFAULT_SPACING, tolerance: float = 0.05) -> dict:
  """The true surface of a real sequence from its labelled GT mesh (ScanNet's
  `*_vh_clean_2.labels.ply`, vertex `label` = NYU40 id): even samples of the mesh
  (`ground_truth.surface_from_mesh`, classes of `label_space`) that the sequence's frames see
  (`seen_points`), as `seen_surface` keeps only what the cameras see.

  Returns:
    dict with `points (G, 3) float64` and `labels (G,) int32`.
  """
  from jaxfusion.datasets import classes  # pylint: disable=import-outside-toplevel
  from jaxfusion.datasets import ground_truth  # pylint: disable=import-outside-toplevel
  from jaxfusion.datasets import plyfile  # pylint: disable=import-outside-toplevel
  mesh = plyfile.read_labelled_mesh(path)
  _, lut = classes.label_space(label_space)
  surface = ground_truth.surface_from_mesh(mesh["vertices"], mesh["faces"], mesh["labels"],
                                           lut=lut, spacing=spacing)
  keep = seen_points(surface["points"], sequence, tolerance=tolerance)
  return {"points": surface["points"][keep], "labels": surface["labels"][keep]}
