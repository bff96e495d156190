"""A vectorised, jitted ray caster against analytic primitives.

Each pixel casts the ray `o + t·d` with `d = R_world_cam @ ((u − cx)/fx, (v − cy)/fy, 1)`, so
the ray parameter `t` of a hit *is* the z-depth. Primitives are grouped by kind into tables
padded to static sizes (`pack`), every ray is tested against every primitive of every kind
(rays are processed in fixed-size chunks to bound memory), and the nearest hit wins. A second
pass computes, for the winning primitive only, the hit point, normal and texture coordinates.

Shape legend: H×W pixels, N = H·W rays, P primitives, P_k primitives of one kind.
"""

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxfusion.camera import Camera
from jaxfusion.datasets.primitives import BOX, CYLINDER, PLANE, SPHERE, Primitives

NEAR = 1e-3  # hits closer than this (in z-depth metres) are ignored
_TINY = 1e-9
_CHUNK = 8192  # rays per chunk of the intersection pass


class KindTable(NamedTuple):
  """The primitives of one kind, ready for intersection.

  Attributes:
    index: `(P_k,) int32` row in the full table, `-1` for padding.
    center: `(P_k, 3) float32` local origins.
    inv_frame: `(P_k, 3, 3) float32` `diag(1/half_size) @ R^T`: world offset → unit shape.
  """
  index: jax.Array
  center: jax.Array
  inv_frame: jax.Array


class PackedScene(NamedTuple):
  """A scene ready for `cast`: per-kind tables plus the full attribute table."""
  boxes: KindTable
  cylinders: KindTable
  spheres: KindTable
  planes: KindTable
  prims: Primitives


class Hits(NamedTuple):
  """Per-pixel result of `cast` (all `(H, W, ...)`).

  Attributes:
    depth: `(H, W) float32` z-depth in metres, 0 where nothing was hit.
    prim: `(H, W) int32` row of the hit primitive, -1 where nothing was hit.
    label: `(H, W) int32` class of the hit primitive (0 where nothing was hit).
    instance: `(H, W) int32` instance id (0 where nothing was hit).
    normal: `(H, W, 3) float32` unit world normal facing the camera.
    p_world: `(H, W, 3) float32` hit point.
    p_local: `(H, W, 3) float32` hit point in the primitive's frame, in metres.
    view_dir: `(H, W, 3) float32` unit ray direction in the world.
  """
  depth: jax.Array
  prim: jax.Array
  label: jax.Array
  instance: jax.Array
  normal: jax.Array
  p_world: jax.Array
  p_local: jax.Array
  view_dir: jax.Array


def _bucket(n: int, step: int) -> int:
  return max(step, -(-n // step) * step)


def _kind_table(primitives: Primitives, kind: int, size: int) -> KindTable:
  rows = np.nonzero(primitives.kind == kind)[0]
  index = np.full((size,), -1, np.int32)
  index[:len(rows)] = rows
  center = np.zeros((size, 3), np.float32)
  center[:len(rows)] = primitives.center[rows]
  inv_frame = np.tile(np.eye(3, dtype=np.float32), (size, 1, 1))
  h = primitives.half_size[rows].astype(np.float64)
  if kind == PLANE:
    h = np.ones_like(h)
  inv = np.transpose(primitives.rotation[rows].astype(np.float64), (0, 2, 1)) / h[:, :, None]
  inv_frame[:len(rows)] = inv
  return KindTable(index, center, inv_frame)


def pack(primitives: Primitives, *, step: int = 32) -> PackedScene:
  """Groups a primitive table by kind, padding every group to a multiple of `step`.

  Padding to buckets keeps the number of distinct compiled shapes small when many scenes
  are rendered (for example by `synthetic.sample_views`).

  Args:
    primitives: the scene (host arrays).
    step: bucket size of the per-kind tables and of the full table.

  Returns:
    A `PackedScene` of NumPy arrays (jit turns them into device arrays).
  """
  counts = [int(np.sum(primitives.kind == k)) for k in (BOX, CYLINDER, SPHERE, PLANE)]
  if np.any(~np.isin(primitives.kind, (BOX, CYLINDER, SPHERE, PLANE))):
    raise ValueError("unknown primitive kind in table")
  if np.any(primitives.half_size[primitives.kind != PLANE] <= 0):
    raise ValueError("primitives need positive half sizes")
  tables = [_kind_table(primitives, k, _bucket(c, step if k != PLANE else 8))
            for k, c in zip((BOX, CYLINDER, SPHERE, PLANE), counts)]
  total = _bucket(len(primitives), step)
  pad = total - len(primitives)

  def padded(x, fill):
    return np.concatenate([x, np.full((pad,) + x.shape[1:], fill, x.dtype)])

  prims = Primitives(*(padded(x, 1 if name in ("half_size", "rotation") else 0)
                       for name, x in zip(Primitives._fields, primitives)))
  return PackedScene(*tables, prims)


def _hit_boxes(o, d):
  """`t (N, P)` of rays `o (P, 3)` + t·`d (N, P, 3)` against the unit cube (inf: miss)."""
  d = jnp.where(jnp.abs(d) < _TINY, _TINY, d)
  inv = 1.0 / d
  t1 = (-1.0 - o) * inv
  t2 = (1.0 - o) * inv
  t_near = jnp.max(jnp.minimum(t1, t2), axis=-1)
  t_far = jnp.min(jnp.maximum(t1, t2), axis=-1)
  t = jnp.where(t_near > NEAR, t_near, t_far)
  return jnp.where((t_near <= t_far) & (t > NEAR), t, jnp.inf)


def _hit_spheres(o, d):
  """`t (N, P)` against the unit sphere."""
  a = jnp.sum(d * d, axis=-1)
  b = jnp.sum(o * d, axis=-1)
  c = jnp.sum(o * o, axis=-1) - 1.0
  disc = b * b - a * c
  sq = jnp.sqrt(jnp.maximum(disc, 0.0))
  t1 = (-b - sq) / a
  t2 = (-b + sq) / a
  t = jnp.where(t1 > NEAR, t1, t2)
  return jnp.where((disc >= 0) & (t > NEAR), t, jnp.inf)


def _hit_cylinders(o, d):
  """`t (N, P)` against the capped unit cylinder along z."""
  ox, oy, oz = o[..., 0], o[..., 1], o[..., 2]
  dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
  a = jnp.maximum(dx * dx + dy * dy, _TINY)
  b = ox * dx + oy * dy
  c = ox * ox + oy * oy - 1.0
  disc = b * b - a * c
  sq = jnp.sqrt(jnp.maximum(disc, 0.0))
  best = jnp.inf
  for t in ((-b - sq) / a, (-b + sq) / a):
    ok = (disc >= 0) & (t > NEAR) & (jnp.abs(oz + t * dz) <= 1.0)
    best = jnp.minimum(best, jnp.where(ok, t, jnp.inf))
  dz_safe = jnp.where(jnp.abs(dz) < _TINY, _TINY, dz)
  for cap in (-1.0, 1.0):
    t = (cap - oz) / dz_safe
    x = ox + t * dx
    y = oy + t * dy
    ok = (t > NEAR) & (x * x + y * y <= 1.0)
    best = jnp.minimum(best, jnp.where(ok, t, jnp.inf))
  return best


def _hit_planes(o, d):
  """`t (N, P)` against the plane q_z = 0."""
  dz = d[..., 2]
  dz = jnp.where(jnp.abs(dz) < _TINY, _TINY, dz)
  t = -o[..., 2] / dz
  return jnp.where(t > NEAR, t, jnp.inf)


_HIT_FNS = (_hit_boxes, _hit_cylinders, _hit_spheres, _hit_planes)


def _nearest(table: KindTable, hit_fn, origin, dirs):
  """Nearest hit of rays `dirs (N, 3)` from `origin (3,)` among one kind's primitives."""
  o_local = jnp.einsum("pij,pj->pi", table.inv_frame, origin[None] - table.center)  # (P_k, 3)
  d_local = jnp.einsum("pij,nj->npi", table.inv_frame, dirs)  # (N, P_k, 3)
  t = hit_fn(o_local[None], d_local)
  t = jnp.where(table.index[None] >= 0, t, jnp.inf)
  arg = jnp.argmin(t, axis=-1)
  return jnp.take_along_axis(t, arg[:, None], axis=-1)[:, 0], table.index[arg]


def _first_hits(scene: PackedScene, origin, dirs):
  """`(t (N,), prim (N,))` of the nearest hit over all kinds; prim = -1 where none."""
  ts, idx = [], []
  for table, fn in zip(scene[:4], _HIT_FNS):
    t, i = _nearest(table, fn, origin, dirs)
    ts.append(t)
    idx.append(i)
  ts = jnp.stack(ts, axis=-1)
  idx = jnp.stack(idx, axis=-1)
  arg = jnp.argmin(ts, axis=-1)
  t = jnp.take_along_axis(ts, arg[:, None], axis=-1)[:, 0]
  prim = jnp.take_along_axis(idx, arg[:, None], axis=-1)[:, 0]
  hit = jnp.isfinite(t)
  return jnp.where(hit, t, 0.0), jnp.where(hit, prim, -1)


def pixel_rays(T_world_cam, camera: Camera, height: int, width: int):
  """World rays of all pixels.

  Args:
    T_world_cam: `(4, 4)` camera-to-world pose.
    camera: intrinsics.
    height: image rows H.
    width: image columns W.

  Returns:
    `(origin (3,), dirs (H·W, 3))` float32, with `dirs` scaled so that its camera-frame z is 1.
  """
  T = jnp.asarray(T_world_cam, jnp.float32)
  u = jnp.arange(width, dtype=jnp.float32)[None, :]
  v = jnp.arange(height, dtype=jnp.float32)[:, None]
  x = jnp.broadcast_to((u - camera.cx) / camera.fx, (height, width))
  y = jnp.broadcast_to((v - camera.cy) / camera.fy, (height, width))
  d_cam = jnp.stack([x, y, jnp.ones_like(x)], axis=-1).reshape(-1, 3)
  return T[:3, 3], d_cam @ T[:3, :3].T


@functools.partial(jax.jit, static_argnames=("height", "width"))
def cast(scene: PackedScene, T_world_cam, camera: Camera, *, height: int, width: int) -> Hits:
  """Casts one ray per pixel into the scene.

  Args:
    scene: output of `pack`.
    T_world_cam: `(4, 4) float32` camera-to-world pose.
    camera: intrinsics.
    height: image rows H (static).
    width: image columns W (static).

  Returns:
    `Hits` with `(H, W, ...)` arrays; `depth` is z-depth along the optical axis.
  """
  origin, dirs = pixel_rays(T_world_cam, camera, height, width)
  n = height * width
  chunk = min(_CHUNK, n)
  num_chunks = -(-n // chunk)
  padded = jnp.concatenate([dirs, jnp.tile(dirs[:1], (num_chunks * chunk - n, 1))])
  t, prim = jax.lax.map(lambda ds: _first_hits(scene, origin, ds),
                        padded.reshape(num_chunks, chunk, 3))
  t = t.reshape(-1)[:n]
  prim = prim.reshape(-1)[:n]
  hit = prim >= 0
  g = jnp.maximum(prim, 0)
  p = scene.prims
  p_world = origin[None] + t[:, None] * dirs
  rot = p.rotation[g]  # (N, 3, 3)
  half = p.half_size[g]
  kind = p.kind[g]
  p_local = jnp.einsum("nji,nj->ni", rot, p_world - p.center[g])  # R^T (p − c)
  unit_half = jnp.where((kind == PLANE)[:, None], 1.0, half)
  q = p_local / unit_half
  aq = jnp.abs(q)
  box_axis = jax.nn.one_hot(jnp.argmax(aq, axis=-1), 3) * jnp.sign(q)
  radial = jnp.sqrt(q[:, 0] ** 2 + q[:, 1] ** 2)
  cap = aq[:, 2] > radial
  cyl = jnp.where(cap[:, None], jnp.stack([0 * q[:, 0], 0 * q[:, 0], jnp.sign(q[:, 2])], -1),
                  q * jnp.array([1.0, 1.0, 0.0]))
  plane = jnp.broadcast_to(jnp.array([0.0, 0.0, 1.0]), q.shape)
  n_local = jnp.select([(kind == BOX)[:, None], (kind == CYLINDER)[:, None],
                        (kind == SPHERE)[:, None]], [box_axis, cyl, q], plane)
  normal = jnp.einsum("nij,nj->ni", rot, n_local / unit_half)
  normal = normal / jnp.maximum(jnp.linalg.norm(normal, axis=-1, keepdims=True), _TINY)
  view_dir = dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True)
  normal = jnp.where(jnp.sum(normal * view_dir, -1, keepdims=True) > 0, -normal, normal)
  shape = (height, width)
  return Hits(
      depth=t.reshape(shape).astype(jnp.float32),
      prim=prim.reshape(shape),
      label=jnp.where(hit, p.label[g], 0).reshape(shape),
      instance=jnp.where(hit, p.instance[g], 0).reshape(shape),
      normal=normal.reshape(shape + (3,)),
      p_world=p_world.reshape(shape + (3,)),
      p_local=p_local.reshape(shape + (3,)),
      view_dir=view_dir.reshape(shape + (3,)),
  )
