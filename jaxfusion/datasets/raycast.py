"""A vectorised, jitted ray caster against analytic primitives.

Each pixel casts the ray `o + t·d` with `d = R_world_cam @ ((u − cx)/fx, (v − cy)/fy, 1)`, so
the ray parameter `t` of a hit *is* the z-depth. Primitives are grouped by kind into tables
padded to static sizes (`pack`). On the host, `tile_lists` projects every primitive's bounding
box into the image and lists, for each 16×16 pixel tile, the primitives that may cover it
(padded to a power of two). `cast` then tests each tile's rays against its own candidates only
(vmapped over tiles, `lax.map` over batches of tiles to bound memory) — the same image as
testing every ray against every primitive (`tiles=None`), several times faster. A second pass
computes, for the winning primitive only, the hit point, normal and local coordinates.

Shape legend: H×W pixels, N = H·W rays, P primitives, P_k primitives of one kind,
K_k candidates of one kind per tile.
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
  return -(-n // step) * step


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
  total = max(step, _bucket(len(primitives), step))
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


class TileLists(NamedTuple):
  """Candidate primitives per screen tile, one array per kind.

  Each field is `(num_tiles, K_k) int32`: rows of that kind's `KindTable` whose screen bounds
  overlap the tile, padded with -1. Tiles are `tile × tile` pixels in row-major order.
  """
  boxes: np.ndarray
  cylinders: np.ndarray
  spheres: np.ndarray
  planes: np.ndarray


def screen_bounds(primitives: Primitives, T_world_cam, camera: Camera) -> np.ndarray:
  """Conservative pixel bounds of every primitive's projection.

  Args:
    primitives: the table.
    T_world_cam: `(4, 4)` pose.
    camera: intrinsics.

  Returns:
    `(P, 4) float64` `[u_min, u_max, v_min, v_max]` of the part of each primitive's bounding
    box in front of the near plane (the box clipped at z = NEAR, then projected): the whole
    image plane for planes, an empty box for primitives entirely behind the camera.
  """
  T = np.asarray(T_world_cam, np.float64)
  corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
  local = corners[None] * primitives.half_size.astype(np.float64)[:, None, :]
  p_world = primitives.center[:, None, :] + np.einsum("pij,pcj->pci",
                                                      primitives.rotation.astype(np.float64),
                                                      local)
  p_cam = (p_world - T[:3, 3]) @ T[:3, :3]  # (P, 8, 3)
  # Clip against z ≥ NEAR: keep the corners in front and add where the 12 edges cross it.
  edges = np.array([(a, b) for a in range(8) for b in range(a + 1, 8)
                    if bin(a ^ b).count("1") == 1])
  pa, pb = p_cam[:, edges[:, 0]], p_cam[:, edges[:, 1]]
  za, zb = pa[..., 2], pb[..., 2]
  crosses = (za - NEAR) * (zb - NEAR) < 0
  s = np.where(crosses, (NEAR - za) / np.where(crosses, zb - za, 1.0), 0.0)
  cut = pa + s[..., None] * (pb - pa)
  points = np.concatenate([p_cam, cut], axis=1)  # (P, 20, 3)
  valid = np.concatenate([p_cam[..., 2] >= NEAR, crosses], axis=1)
  z = np.where(valid, np.maximum(points[..., 2], NEAR), 1.0)
  u = camera.fx * points[..., 0] / z + camera.cx
  v = camera.fy * points[..., 1] / z + camera.cy
  lo = lambda x: np.where(valid, x, np.inf).min(1)
  hi = lambda x: np.where(valid, x, -np.inf).max(1)
  bounds = np.stack([lo(u), hi(u), lo(v), hi(v)], -1)
  everywhere = np.array([-np.inf, np.inf, -np.inf, np.inf])
  return np.where((primitives.kind == PLANE)[:, None], everywhere, bounds)


def _pow2_at_least(n: int) -> int:
  return 0 if n == 0 else max(8, 1 << (int(n) - 1).bit_length())


def tile_lists(scene: PackedScene, T_world_cam, camera: Camera, *, height: int, width: int,
               tile: int = 16, min_sizes=(0, 0, 0, 0), candidates=None) -> TileLists:
  """Per-tile candidate lists for `cast` (host-side NumPy).

  Args:
    scene: output of `pack`.
    T_world_cam: `(4, 4)` pose.
    camera: intrinsics.
    height: image rows H.
    width: image columns W.
    tile: tile edge in pixels.
    min_sizes: lower bounds of the per-kind list lengths; pass the maximum over a sequence to
      give every frame the same shapes (one compilation).
    candidates: optional `(P,) bool` over the rows of `scene.prims` (its padding included or
      not): only these primitives may enter a list (None: all). A caller that knows some
      primitives cannot be seen (e.g. beyond a sensor's range) leaves them out.

  Returns:
    `TileLists` whose lengths are powers of two (≥ 8, or 0 for a kind no tile sees).
  """
  prims = Primitives(*(np.asarray(x) for x in scene.prims))
  bounds = screen_bounds(prims, T_world_cam, camera)
  keep = None
  if candidates is not None:
    keep = np.zeros(len(prims), bool)
    given = np.asarray(candidates, bool).reshape(-1)[:len(prims)]
    keep[:len(given)] = given
  ty = np.arange(-(-height // tile)) * tile
  tx = np.arange(-(-width // tile)) * tile
  lists = []
  for table, min_size in zip(scene[:4], min_sizes):
    rows = np.asarray(table.index)
    b = bounds[np.maximum(rows, 0)]
    over_u = (b[None, :, 1] >= tx[:, None] - 1) & (b[None, :, 0] <= tx[:, None] + tile)
    over_v = (b[None, :, 3] >= ty[:, None] - 1) & (b[None, :, 2] <= ty[:, None] + tile)
    mask = (over_v[:, None, :] & over_u[None, :, :]).reshape(len(ty) * len(tx), -1)
    mask &= rows[None] >= 0
    if keep is not None:
      mask &= keep[np.maximum(rows, 0)][None]
    size = _pow2_at_least(max(int(mask.sum(1).max(initial=0)), int(min_size)))
    order = np.argsort(~mask, axis=1, kind="stable")[:, :size]
    picked = np.take_along_axis(mask, order, axis=1)
    out = np.full((mask.shape[0], size), -1, np.int32)
    out[:, :order.shape[1]] = np.where(picked, order, -1)
    lists.append(out)
  return TileLists(*lists)


def list_sizes(lists: TileLists) -> tuple:
  """The per-kind list lengths `(K_box, K_cyl, K_sph, K_plane)` of a `TileLists`."""
  return tuple(int(x.shape[1]) for x in lists)


def _nearest(center, inv_frame, index, hit_fn, origin, dirs):
  """Nearest hit of rays `dirs (N, 3)` from `origin (3,)` among `K` primitives of one kind.

  `center (K, 3)`, `inv_frame (K, 3, 3)`, `index (K,)` (row in the full table, -1 = none).
  """
  o_local = jnp.einsum("pij,pj->pi", inv_frame, origin[None] - center)  # (K, 3)
  d_local = jnp.einsum("pij,nj->npi", inv_frame, dirs)  # (N, K, 3)
  t = hit_fn(o_local[None], d_local)
  t = jnp.where(index[None] >= 0, t, jnp.inf)
  arg = jnp.argmin(t, axis=-1)
  return jnp.take_along_axis(t, arg[:, None], axis=-1)[:, 0], index[arg]


def _first_hits(tables, origin, dirs):
  """`(t (N,), prim (N,))` of the nearest hit over all kinds; prim = -1 where none.

  `tables` holds one `(center, inv_frame, index)` triple per kind (in `_HIT_FNS` order).
  """
  ts = [jnp.full(dirs.shape[:1], jnp.inf)]
  idx = [jnp.full(dirs.shape[:1], -1, jnp.int32)]
  for (center, inv_frame, index), fn in zip(tables, _HIT_FNS):
    if index.shape[0] == 0:
      continue
    t, i = _nearest(center, inv_frame, index, fn, origin, dirs)
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
    `(origin (3,), dirs (H, W, 3))` float32, with `dirs` scaled so that its camera-frame z is 1.
  """
  T = jnp.asarray(T_world_cam, jnp.float32)
  u = jnp.arange(width, dtype=jnp.float32)[None, :]
  v = jnp.arange(height, dtype=jnp.float32)[:, None]
  x = jnp.broadcast_to((u - camera.cx) / camera.fx, (height, width))
  y = jnp.broadcast_to((v - camera.cy) / camera.fy, (height, width))
  d_cam = jnp.stack([x, y, jnp.ones_like(x)], axis=-1)
  return T[:3, 3], d_cam @ T[:3, :3].T


def _cast_all(scene: PackedScene, origin, dirs):
  """Every ray against every primitive, in chunks of `_CHUNK` rays."""
  n = dirs.shape[0]
  chunk = min(_CHUNK, n)
  num_chunks = -(-n // chunk)
  padded = jnp.concatenate([dirs, jnp.tile(dirs[:1], (num_chunks * chunk - n, 1))])
  tables = [(t.center, t.inv_frame, t.index) for t in scene[:4]]
  t, prim = jax.lax.map(lambda ds: _first_hits(tables, origin, ds),
                        padded.reshape(num_chunks, chunk, 3))
  return t.reshape(-1)[:n], prim.reshape(-1)[:n]


def _cast_tiled(scene: PackedScene, tiles: TileLists, origin, dirs_img, tile: int):
  """Rays of each screen tile against that tile's candidate primitives only."""
  height, width = dirs_img.shape[:2]
  nty, ntx = -(-height // tile), -(-width // tile)
  padded = jnp.pad(dirs_img, ((0, nty * tile - height), (0, ntx * tile - width), (0, 0)),
                   mode="edge")
  rays = padded.reshape(nty, tile, ntx, tile, 3).transpose(0, 2, 1, 3, 4)
  rays = rays.reshape(nty * ntx, tile * tile, 3)
  per_tile = []
  for table, rows in zip(scene[:4], tiles):
    rows = jnp.asarray(rows)
    r = jnp.maximum(rows, 0)
    index = jnp.where(rows >= 0, table.index[r], -1) if rows.shape[1] else rows
    per_tile.append((table.center[r], table.inv_frame[r], index))

  def one_tile(args):
    tables, ds = args
    return _first_hits(tables, origin, ds)

  batch = max(1, _CHUNK // (tile * tile))
  t, prim = jax.lax.map(one_tile, (per_tile, rays), batch_size=batch)
  unflat = lambda x: x.reshape(nty, ntx, tile, tile).transpose(0, 2, 1, 3).reshape(
      nty * tile, ntx * tile)[:height, :width].reshape(-1)
  return unflat(t), unflat(prim)


@functools.partial(jax.jit, static_argnames=("height", "width", "tile"))
def cast(scene: PackedScene, T_world_cam, camera: Camera, *, height: int, width: int,
         tiles=None, tile: int = 16) -> Hits:
  """Casts one ray per pixel into the scene.

  Args:
    scene: output of `pack`.
    T_world_cam: `(4, 4) float32` camera-to-world pose.
    camera: intrinsics.
    height: image rows H (static).
    width: image columns W (static).
    tiles: optional `TileLists` from `tile_lists` for this pose: each `tile × tile` block of
      pixels is then tested only against the primitives that may project into it (the same
      image, several times faster). None tests every ray against every primitive.
    tile: the tile edge the lists were made for (static).

  Returns:
    `Hits` with `(H, W, ...)` arrays; `depth` is z-depth along the optical axis.
  """
  origin, dirs_img = pixel_rays(T_world_cam, camera, height, width)
  dirs = dirs_img.reshape(-1, 3)
  if tiles is None:
    t, prim = _cast_all(scene, origin, dirs)
  else:
    t, prim = _cast_tiled(scene, tiles, origin, dirs_img, tile)
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
