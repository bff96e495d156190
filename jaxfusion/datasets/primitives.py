"""Analytic primitives: the table the ray caster renders, and helpers to build it.

A scene is a flat table of P primitives. Every primitive lives in its own local frame,
`p_world = center + rotation @ (half_size * q)`, where `q` is the primitive in unit size:

* `BOX`: the cube `[-1, 1]^3`;
* `CYLINDER`: `x² + y² ≤ 1, |z| ≤ 1` (axis along local z, capped);
* `SPHERE`: `|q| ≤ 1` (an ellipsoid once scaled);
* `PLANE`: the infinite plane `q_z = 0` (two-sided), used for floors, walls and ceilings.

Shape legend: P primitives.
"""

from typing import NamedTuple

import numpy as np

BOX, CYLINDER, SPHERE, PLANE = 0, 1, 2, 3
KIND_NAMES = ("box", "cylinder", "sphere", "plane")

# Procedural texture ids (see `appearance.texture`).
PLAIN, STRIPES, CHECKER, WOOD, NOISE, SCREEN = range(6)


class Material(NamedTuple):
  """Appearance of one primitive.

  Attributes:
    color: `(3,) float` base albedo in [0, 1].
    color2: `(3,) float` secondary colour of the texture pattern.
    texture: texture id (`PLAIN`, `STRIPES`, `CHECKER`, `WOOD`, `NOISE`, `SCREEN`).
    scale: texture frequency in cycles per metre.
    emission: self-illumination in [0, 1] (lamps, windows, screens).
    gloss: strength in [0, 1] of the sharp specular lobe that `sensing` adds (0: matte, such
      as fabric or cardboard; 1: glass, lacquer, polished metal).
  """
  color: np.ndarray
  color2: np.ndarray
  texture: int
  scale: float
  emission: float
  gloss: float = 0.0


class Primitives(NamedTuple):
  """A scene as a table of primitives (host-side NumPy arrays).

  Attributes:
    kind: `(P,) int32` one of `BOX`, `CYLINDER`, `SPHERE`, `PLANE`.
    center: `(P, 3) float32` world position of the local origin.
    rotation: `(P, 3, 3) float32` world-from-local rotation.
    half_size: `(P, 3) float32` half extents along the local axes (radius for round axes).
    label: `(P,) int32` semantic class.
    instance: `(P,) int32` instance id (≥ 1; 0 is reserved for "no hit").
    color: `(P, 3) float32` base albedo.
    color2: `(P, 3) float32` secondary texture colour.
    texture: `(P,) int32` texture id.
    texture_scale: `(P,) float32` texture frequency in cycles per metre.
    emission: `(P,) float32` self-illumination.
    gloss: `(P,) float32` glossiness of the material (see `Material.gloss`).
  """
  kind: np.ndarray
  center: np.ndarray
  rotation: np.ndarray
  half_size: np.ndarray
  label: np.ndarray
  instance: np.ndarray
  color: np.ndarray
  color2: np.ndarray
  texture: np.ndarray
  texture_scale: np.ndarray
  emission: np.ndarray
  gloss: np.ndarray

  def __len__(self) -> int:
    return int(self.kind.shape[0])


class Part(NamedTuple):
  """One primitive of an object, in the object's local frame (before label/instance)."""
  kind: int
  center: np.ndarray
  rotation: np.ndarray
  half_size: np.ndarray
  material: Material


def rot_z(yaw: float) -> np.ndarray:
  """`(3, 3) float64` rotation by `yaw` radians about +z."""
  c, s = np.cos(yaw), np.sin(yaw)
  return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def rot_x(angle: float) -> np.ndarray:
  """`(3, 3) float64` rotation by `angle` radians about +x."""
  c, s = np.cos(angle), np.sin(angle)
  return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> np.ndarray:
  """`(3, 3) float64` rotation by `angle` radians about +y."""
  c, s = np.cos(angle), np.sin(angle)
  return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def part(kind: int, center, half_size, material: Material, *, rotation=None) -> Part:
  """A `Part` from plain sequences (rotation defaults to identity)."""
  rotation = np.eye(3) if rotation is None else np.asarray(rotation, np.float64)
  return Part(kind, np.asarray(center, np.float64), rotation,
              np.asarray(half_size, np.float64), material)


def box_on(material: Material, x, y, z0, sx, sy, sz, *, rotation=None) -> Part:
  """An axis-aligned (in the object frame) box of full size `(sx, sy, sz)` standing on `z0`."""
  return part(BOX, (x, y, z0 + sz / 2), (sx / 2, sy / 2, sz / 2), material, rotation=rotation)


def cylinder_on(material: Material, x, y, z0, radius, height, *, radius_y=None) -> Part:
  """A vertical cylinder of `radius` and `height` standing on `z0`."""
  radius_y = radius if radius_y is None else radius_y
  return part(CYLINDER, (x, y, z0 + height / 2), (radius, radius_y, height / 2), material)


def place(parts, position, yaw: float, label: int, instance: int) -> list:
  """Moves object parts into the world.

  Args:
    parts: list of `Part` in the object frame (origin on the floor/support, front = +y).
    position: `(3,)` world position of the object origin.
    yaw: rotation about +z in radians.
    label: class of every part.
    instance: instance id of every part.

  Returns:
    list of `(Part, label, instance)` in world coordinates.
  """
  R = rot_z(yaw)
  position = np.asarray(position, np.float64)
  return [(Part(p.kind, position + R @ p.center, R @ p.rotation, p.half_size, p.material),
           label, instance) for p in parts]


def to_table(placed) -> Primitives:
  """Stacks `(Part, label, instance)` triples into a `Primitives` table."""
  if not placed:
    raise ValueError("a scene needs at least one primitive")
  f32 = lambda xs: np.asarray(xs, np.float32)
  parts = [p for p, _, _ in placed]
  return Primitives(
      kind=np.asarray([p.kind for p in parts], np.int32),
      center=f32([p.center for p in parts]),
      rotation=f32([p.rotation for p in parts]),
      half_size=f32([p.half_size for p in parts]),
      label=np.asarray([lab for _, lab, _ in placed], np.int32),
      instance=np.asarray([ins for _, _, ins in placed], np.int32),
      color=f32([p.material.color for p in parts]),
      color2=f32([p.material.color2 for p in parts]),
      texture=np.asarray([p.material.texture for p in parts], np.int32),
      texture_scale=f32([p.material.scale for p in parts]),
      emission=f32([p.material.emission for p in parts]),
      gloss=f32([p.material.gloss for p in parts]),
  )


def surface_distance(primitives: Primitives, p_world: np.ndarray) -> np.ndarray:
  """Distance of points to the nearest primitive surface (for tests and checks).

  Exact for planes and boxes; for cylinders and ellipsoids the distance is measured in
  metres after scaling to the unit shape, which is exact for circular cylinders and spheres
  and a close bound otherwise.

  Args:
    primitives: the scene.
    p_world: `(N, 3)` world points.

  Returns:
    `(N,) float64` distance of every point to the closest primitive surface.
  """
  p = np.asarray(p_world, np.float64)[:, None, :] - primitives.center[None].astype(np.float64)
  local = np.einsum("npi,pij->npj", p, primitives.rotation.astype(np.float64))  # R^T p
  h = primitives.half_size.astype(np.float64)[None]
  kind = primitives.kind[None]
  # Box: signed distance to the box surface, taken as an absolute value.
  qb = np.abs(local) - h
  outside = np.linalg.norm(np.maximum(qb, 0.0), axis=-1)
  inside = np.minimum(np.max(qb, axis=-1), 0.0)
  d_box = np.abs(outside + inside)
  # Cylinder (z axis): radial and axial offsets.
  radial = np.linalg.norm(local[..., :2] / h[..., :2], axis=-1) * np.min(h[..., :2], axis=-1)
  r = np.min(h[..., :2], axis=-1)
  dr = radial - r
  dz = np.abs(local[..., 2]) - h[..., 2]
  d_cyl = np.abs(np.minimum(np.maximum(dr, dz), 0.0)
                 + np.linalg.norm(np.stack([np.maximum(dr, 0), np.maximum(dz, 0)], -1), axis=-1))
  # Sphere / ellipsoid: scaled radial distance.
  rs = np.min(h, axis=-1)
  d_sph = np.abs(np.linalg.norm(local / h, axis=-1) - 1.0) * rs
  d_plane = np.abs(local[..., 2])
  d = np.select([kind == BOX, kind == CYLINDER, kind == SPHERE], [d_box, d_cyl, d_sph], d_plane)
  return d.min(axis=1)
