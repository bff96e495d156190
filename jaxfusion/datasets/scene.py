"""Procedural indoor scenes: room layouts ("office", "house") and parametric furniture.

A scene is built in two steps, so that the same furniture can be shown in either appearance
domain:

1. `make_layout(env, seed)` draws the room and the placement of every object (class,
   position, yaw, nominal size and a vector of uniform draws). It depends on `(env, seed)`
   only.
2. `build_primitives(layout, s)` turns the placements into analytic primitives. The domain
   weight `s` (see `appearance.domain_shift`) changes palettes, textures and the within-class
   proportions (chair backs, leg styles, table tops, sofa arms, TV aspect, bottle and plant
   shapes), never where objects stand.

Object frames: the origin is on the supporting surface at the footprint centre, +z up, and
the object's front faces +y (the side a person sits on, the side a screen shows).
The room spans `[0, Lx] × [0, Ly] × [0, H]`; walls are indexed 0: y = 0, 1: x = Lx, 2: y = Ly,
3: x = 0.
"""

from typing import NamedTuple

import numpy as np

from jaxfusion.datasets import appearance
from jaxfusion.datasets.appearance import lerp
from jaxfusion.datasets.classes import BACKGROUND, BOTTLE, CHAIR, PLANT, SOFA, TABLE, TV
from jaxfusion.datasets.primitives import (CYLINDER, PLANE, SPHERE, Primitives, box_on,
                                           cylinder_on, part, place, rot_x, rot_y, rot_z,
                                           to_table)

ENVIRONMENTS = ("office", "house")
_NUM_U = 24  # uniform draws per placement: 8 for shape, 16 for materials (4 slots × 4)


class Placement(NamedTuple):
  """One object of a layout.

  Attributes:
    kind: builder name (a key of `BUILDERS`).
    label: class index (see `classes.CLASS_NAMES`).
    instance: instance id ≥ 1.
    position: `(3,)` world position of the object origin.
    yaw: rotation about +z (radians).
    size: `(3,)` nominal width, depth and height in metres.
    u: `(24,)` uniform draws that fix proportions and material picks.
  """
  kind: str
  label: int
  instance: int
  position: np.ndarray
  yaw: float
  size: np.ndarray
  u: np.ndarray


class Layout(NamedTuple):
  """A room and its objects, independent of the appearance domain.

  Attributes:
    env: "office" or "house".
    seed: the seed it was drawn from.
    room: `(3,)` room size `(Lx, Ly, H)` in metres.
    placements: tuple of `Placement`.
    light_u: `(4,)` uniforms of the lighting.
  """
  env: str
  seed: int
  room: np.ndarray
  placements: tuple
  light_u: np.ndarray


def _prop(u: float, train_range, test_range, s: float) -> float:
  """A proportion drawn at quantile `u` of the train range, moved `s` towards the test range."""
  return float(lerp(lerp(train_range[0], train_range[1], u),
                    lerp(test_range[0], test_range[1], u), s))


def _mat(pl: Placement, slot_index: int, slot: str, s: float, emission: float = 0.0):
  return appearance.material(slot, pl.u[8 + 4 * slot_index: 12 + 4 * slot_index], s,
                             emission=emission)


# ----------------------------------------------------------------------------- furniture


def _chair(pl: Placement, s: float) -> list:
  u = pl.u
  w, d = pl.size[0], pl.size[1]
  main, legs = _mat(pl, 0, "chair", s), _mat(pl, 1, "chair_legs", s)
  seat_h = _prop(u[0], (0.44, 0.48), (0.38, 0.44), s)
  seat_t = _prop(u[1], (0.04, 0.06), (0.08, 0.12), s)
  back_h = _prop(u[2], (0.42, 0.55), (0.2, 0.3), s)
  back_t = _prop(u[1], (0.03, 0.05), (0.07, 0.1), s)
  parts = [box_on(main, 0, 0, seat_h - seat_t, w, d, seat_t),
           box_on(main, 0, -d / 2 + back_t / 2, seat_h, w * _prop(u[3], (0.9, 1.0), (0.7, 0.85), s),
                  back_t, back_h)]
  if u[4] < 0.8 * s:  # office-chair pedestal: one column on a round foot
    parts += [cylinder_on(legs, 0, 0, 0.03, 0.03, seat_h - seat_t - 0.03),
              cylinder_on(legs, 0, 0, 0.0, 0.27, 0.03)]
  else:
    leg = _prop(u[5], (0.025, 0.035), (0.035, 0.05), s)
    round_legs = u[6] < s
    for sx in (-1, 1):
      for sy in (-1, 1):
        x, y = sx * (w / 2 - leg), sy * (d / 2 - leg)
        if round_legs:
          parts.append(cylinder_on(legs, x, y, 0.0, leg * 0.8, seat_h - seat_t))
        else:
          parts.append(box_on(legs, x, y, 0.0, leg, leg, seat_h - seat_t))
  if u[7] < 0.6 * s:  # armrests
    for sx in (-1, 1):
      parts.append(box_on(main, sx * (w / 2 - 0.03), 0.0, seat_h + 0.18, 0.06, d * 0.8, 0.05))
  return parts


def _table(pl: Placement, s: float) -> list:
  u = pl.u
  w, d = pl.size[0], pl.size[1]
  top_mat, leg_mat = _mat(pl, 0, "table", s), _mat(pl, 1, "table_legs", s)
  height = pl.size[2]  # fixed: other objects stand on the top
  top_t = _prop(u[1], (0.03, 0.045), (0.05, 0.09), s)
  round_top = u[2] < 0.5 * s and pl.size[2] > 0.6 and w < 1.7
  if round_top:
    parts = [cylinder_on(top_mat, 0, 0, height - top_t, w / 2, top_t, radius_y=d / 2),
             cylinder_on(leg_mat, 0, 0, 0.02, 0.06, height - top_t - 0.02),
             cylinder_on(leg_mat, 0, 0, 0.0, min(w, d) * 0.3, 0.03)]
    return parts
  parts = [box_on(top_mat, 0, 0, height - top_t, w, d, top_t)]
  if u[3] < 0.6 * s:  # panel (trestle) legs at both ends
    panel = _prop(u[4], (0.03, 0.04), (0.04, 0.06), s)
    for sx in (-1, 1):
      parts.append(box_on(leg_mat, sx * (w / 2 - 0.06), 0, 0.0, panel, d * 0.85, height - top_t))
    return parts
  leg = _prop(u[4], (0.04, 0.055), (0.05, 0.08), s)
  inset = _prop(u[5], (0.03, 0.06), (0.08, 0.14), s)
  for sx in (-1, 1):
    for sy in (-1, 1):
      x, y = sx * (w / 2 - inset - leg / 2), sy * (d / 2 - inset - leg / 2)
      if u[6] < s:
        parts.append(cylinder_on(leg_mat, x, y, 0.0, leg / 2, height - top_t))
      else:
        parts.append(box_on(leg_mat, x, y, 0.0, leg, leg, height - top_t))
  return parts


def _sofa(pl: Placement, s: float) -> list:
  u = pl.u
  w, d = pl.size[0], pl.size[1]
  main, legs = _mat(pl, 0, "sofa", s), _mat(pl, 1, "chair_legs", s)
  cushion_mat = _mat(pl, 2, "sofa", s * 0.5)
  lift = _prop(u[0], (0.0, 0.02), (0.1, 0.15), s)
  base_h = _prop(u[1], (0.36, 0.42), (0.22, 0.28), s)
  back_h = _prop(u[2], (0.4, 0.48), (0.28, 0.36), s)
  back_t = _prop(u[3], (0.18, 0.24), (0.12, 0.16), s)
  arm_w = _prop(u[4], (0.16, 0.22), (0.1, 0.14), s)
  arm_h = _prop(u[5], (0.18, 0.24), (0.1, 0.16), s)
  parts = [box_on(main, 0, 0, lift, w, d, base_h),
           box_on(main, 0, -d / 2 + back_t / 2, lift + base_h, w, back_t, back_h)]
  seat_w = w - 2 * arm_w
  n_cushions = 3 if u[6] >= s else 1
  for i in range(n_cushions):
    cw = seat_w / n_cushions
    x = -seat_w / 2 + cw * (i + 0.5)
    parts.append(box_on(cushion_mat, x, back_t / 2, lift + base_h, cw * 0.96, d - back_t, 0.1))
  for sx in (-1, 1):
    x = sx * (w / 2 - arm_w / 2)
    if u[7] < s:  # rolled arms: a horizontal cylinder along the depth
      r = arm_w * 0.9
      parts.append(box_on(main, x, 0, lift + base_h, arm_w, d, arm_h))
      parts.append(part(CYLINDER, (x, 0, lift + base_h + arm_h), (r, r, d / 2), main,
                        rotation=rot_x(np.pi / 2)))
    else:
      parts.append(box_on(main, x, 0, lift + base_h, arm_w, d, arm_h))
  if lift > 0.03:
    for sx in (-1, 1):
      for sy in (-1, 1):
        parts.append(cylinder_on(legs, sx * (w / 2 - 0.08), sy * (d / 2 - 0.08), 0.0, 0.02, lift))
  return parts


def _tv(pl: Placement, s: float) -> list:
  u = pl.u
  w = pl.size[0]
  frame, screen = _mat(pl, 0, "tv_frame", s), _mat(pl, 1, "tv_screen", s, emission=0.6 * s)
  aspect = _prop(u[0], (0.56, 0.6), (0.42, 0.5), s)
  thick = _prop(u[1], (0.05, 0.07), (0.015, 0.025), s)
  bezel = _prop(u[2], (0.025, 0.04), (0.006, 0.012), s)
  h = w * aspect
  if u[3] < 0.7 * s:  # two feet at the sides
    lift = 0.05
    parts = [box_on(frame, sx * w * 0.38, 0, 0.0, 0.03, 0.16, lift + 0.05) for sx in (-1, 1)]
  else:
    lift = _prop(u[4], (0.08, 0.14), (0.05, 0.08), s)
    parts = [box_on(frame, 0, 0, 0.0, w * 0.35, 0.18, 0.015),
             box_on(frame, 0, -0.01, 0.0, 0.05, 0.03, lift + h * 0.3)]
  parts.append(box_on(frame, 0, 0, lift, w, thick, h))
  parts.append(box_on(screen, 0, thick / 2 + 0.003, lift + bezel, w - 2 * bezel, 0.006,
                      h - 2 * bezel))
  return parts


def _bottle(pl: Placement, s: float) -> list:
  u = pl.u
  body, cap = _mat(pl, 0, "bottle", s), _mat(pl, 1, "bottle_cap", s)
  r = _prop(u[0], (0.03, 0.04), (0.04, 0.055), s)
  h = _prop(u[1], (0.18, 0.26), (0.12, 0.18), s)
  neck_r = _prop(u[2], (0.012, 0.016), (0.016, 0.022), s)
  neck_h = _prop(u[3], (0.06, 0.09), (0.03, 0.05), s)
  if u[4] < 0.4 * s:
    parts = [box_on(body, 0, 0, 0.0, 2 * r, 1.4 * r, h)]
  else:
    parts = [cylinder_on(body, 0, 0, 0.0, r, h)]
  if u[5] < s:  # round shoulder
    parts.append(part(SPHERE, (0, 0, h), (r, r, r * 0.6), body))
  parts.append(cylinder_on(body, 0, 0, h, neck_r, neck_h))
  parts.append(cylinder_on(cap, 0, 0, h + neck_h, neck_r * 1.15, 0.02))
  return parts


def _plant(pl: Placement, s: float) -> list:
  u = pl.u
  k = pl.size[2]  # overall scale: 1 for floor plants, ~0.35 for table plants
  leaves, pot = _mat(pl, 0, "foliage", s), _mat(pl, 1, "pot", s)
  leaves2 = _mat(pl, 2, "foliage", s)
  pot_r = k * _prop(u[0], (0.13, 0.17), (0.15, 0.2), s)
  pot_h = k * _prop(u[1], (0.22, 0.3), (0.32, 0.42), s)
  parts = [cylinder_on(pot, 0, 0, 0.0, pot_r * 0.85, pot_h),
           cylinder_on(pot, 0, 0, pot_h - 0.03 * k, pot_r, 0.04 * k)]
  if u[2] >= s:  # bushy: a few round blobs
    r = k * _prop(u[3], (0.24, 0.32), (0.2, 0.26), s)
    parts.append(part(SPHERE, (0, 0, pot_h + r * 0.9), (r, r, r * 0.95), leaves))
    parts.append(part(SPHERE, (r * 0.5, r * 0.2, pot_h + r * 1.5), (r * 0.7,) * 3, leaves2))
    parts.append(part(SPHERE, (-r * 0.45, -r * 0.3, pot_h + r * 1.4), (r * 0.65,) * 3, leaves))
  else:  # columnar with long leaves
    hh = k * _prop(u[3], (0.3, 0.38), (0.36, 0.45), s)
    parts.append(part(SPHERE, (0, 0, pot_h + hh), (0.16 * k, 0.16 * k, hh), leaves))
    for i in range(4):
      a = 2 * np.pi * (i + u[4]) / 4
      tilt = rot_z(a) @ rot_y(0.6)
      c = np.array([np.cos(a) * 0.15 * k, np.sin(a) * 0.15 * k, pot_h + 0.25 * k])
      parts.append(part(SPHERE, c, (0.05 * k, 0.05 * k, 0.26 * k), leaves2, rotation=tilt))
  return parts


# ------------------------------------------------------------------------------ clutter


def _shelf(pl: Placement, s: float) -> list:
  u = pl.u
  w, d, h = pl.size
  mat, items = _mat(pl, 0, "shelf", s), _mat(pl, 1, "cardboard", s)
  t = 0.025
  parts = [box_on(mat, sx * (w / 2 - t / 2), 0, 0.0, t, d, h) for sx in (-1, 1)]
  parts.append(box_on(mat, 0, -d / 2 + 0.005, 0.0, w, 0.01, h))
  n = 4 + int(u[0] * 2)
  for i in range(n):
    z = h * i / (n - 1) - (t if i == n - 1 else 0.0)
    parts.append(box_on(mat, 0, 0, z, w - 2 * t, d, t))
    if 0 < i < n - 1 and u[1 + i % 6] > 0.4:  # a box of files on this board
      bw = 0.2 + 0.3 * u[2 + i % 5]
      parts.append(box_on(items, (u[3 + i % 4] - 0.5) * (w - bw - 0.1), 0.02, z + t,
                          bw, d * 0.7, min(0.25, h / n - 0.08)))
  return parts


def _cabinet(pl: Placement, s: float) -> list:
  w, d, h = pl.size
  mat, metal = _mat(pl, 0, "shelf", s), _mat(pl, 1, "metal", s)
  parts = [box_on(mat, 0, 0, 0.06, w, d, h - 0.06),
           box_on(metal, 0, 0, 0.0, w - 0.1, d - 0.1, 0.06)]
  for sx in (-1, 1):
    parts.append(box_on(metal, sx * w * 0.1, d / 2 + 0.01, h * 0.6, 0.02, 0.02, 0.12))
  return parts


def _box(pl: Placement, s: float) -> list:
  w, d, h = pl.size
  mat = _mat(pl, 0, "cardboard", s)
  parts = [box_on(mat, 0, 0, 0.0, w, d, h)]
  if pl.u[0] > 0.5:
    parts.append(box_on(_mat(pl, 1, "cardboard", s), 0.03, -0.02, h, w * 0.7, d * 0.75, h * 0.7,
                        rotation=rot_z(0.3 * (pl.u[1] - 0.5))))
  return parts


def _floor_lamp(pl: Placement, s: float) -> list:
  h = pl.size[2]
  metal, shade = _mat(pl, 0, "metal", s), _mat(pl, 1, "lamp", s, emission=0.5)
  return [cylinder_on(metal, 0, 0, 0.0, 0.16, 0.03), cylinder_on(metal, 0, 0, 0.03, 0.015, h - 0.3),
          cylinder_on(shade, 0, 0, h - 0.32, 0.18 + 0.05 * pl.u[0], 0.3)]


def _trash_bin(pl: Placement, s: float) -> list:
  return [cylinder_on(_mat(pl, 0, "metal", s), 0, 0, 0.0, 0.14, 0.35)]


def _vase(pl: Placement, s: float) -> list:
  u = pl.u
  mat = _mat(pl, 0, "pot", s)
  r = 0.05 + 0.04 * u[0]
  return [part(SPHERE, (0, 0, r), (r, r, r), mat), cylinder_on(mat, 0, 0, r * 1.6, r * 0.4, 0.1)]


def _stool(pl: Placement, s: float) -> list:
  mat, legs = _mat(pl, 0, "shelf", s), _mat(pl, 1, "metal", s)
  h = pl.size[2]
  parts = [cylinder_on(mat, 0, 0, h - 0.04, 0.17, 0.04)]
  for i in range(3):
    a = 2 * np.pi * i / 3
    parts.append(cylinder_on(legs, 0.11 * np.cos(a), 0.11 * np.sin(a), 0.0, 0.015, h - 0.04))
  return parts


def _wall_panel(pl: Placement, s: float) -> list:
  """A picture or whiteboard hung on a wall (origin at the wall, panel bottom at z)."""
  w, d, h = pl.size
  slot = "picture" if pl.kind == "picture" else "frame"
  frame, art = _mat(pl, 0, "frame", s), _mat(pl, 1, slot, s)
  return [box_on(frame, 0, d / 2, 0.0, w, d, h),
          box_on(art, 0, d + 0.002, 0.03, w - 0.06, 0.004, h - 0.06)]


def _door(pl: Placement, s: float) -> list:
  w, d, h = pl.size
  mat, metal, frame = _mat(pl, 0, "door", s), _mat(pl, 1, "metal", s), _mat(pl, 2, "frame", s)
  return [box_on(frame, 0, 0.0, 0.0, w + 0.12, d, h + 0.06),
          box_on(mat, 0, 0.01, 0.0, w, d, h),
          part(CYLINDER, (w * 0.38, d / 2 + 0.04, 1.0), (0.012, 0.012, 0.06), metal,
               rotation=rot_x(np.pi / 2))]


def _window(pl: Placement, s: float) -> list:
  w, d, h = pl.size
  glass, frame = _mat(pl, 0, "window", s, emission=0.75), _mat(pl, 1, "frame", s)
  t = 0.05
  parts = [box_on(glass, 0, 0.0, 0.0, w, d, h)]
  parts += [box_on(frame, 0, d / 2, z, w + 2 * t, 0.03, t) for z in (-t, h, h / 2 - t / 2)]
  parts += [box_on(frame, sx * (w / 2 + t / 2), d / 2, -t, t, 0.03, h + 2 * t) for sx in (-1, 1)]
  return parts


def _rug(pl: Placement, s: float) -> list:
  w, d, _ = pl.size
  return [box_on(_mat(pl, 0, "rug", s), 0, 0, 0.0, w, d, 0.012)]


def _light_panel(pl: Placement, s: float) -> list:
  w, d, _ = pl.size
  return [box_on(_mat(pl, 0, "light_panel", s, emission=0.9), 0, 0, -0.02, w, d, 0.02)]


BUILDERS = {
    "chair": _chair, "table": _table, "sofa": _sofa, "tv": _tv, "bottle": _bottle,
    "plant": _plant, "shelf": _shelf, "cabinet": _cabinet, "box": _box,
    "floor_lamp": _floor_lamp, "trash_bin": _trash_bin, "vase": _vase, "stool": _stool,
    "picture": _wall_panel, "whiteboard": _wall_panel, "door": _door, "window": _window,
    "rug": _rug, "light_panel": _light_panel,
}


# ------------------------------------------------------------------------------- layout


class _Planner:
  """Collision bookkeeping while a layout is drawn (local to one `make_layout` call)."""

  def __init__(self, rng: np.random.Generator, room: np.ndarray):
    self.rng = rng
    self.room = room
    self.circles = []  # (x, y, r, instance) of floor footprints
    self.wall_low = {w: [] for w in range(4)}  # occupied intervals at floor level
    self.wall_high = {w: [] for w in range(4)}  # occupied intervals at eye level
    self.placements = []

  def wall_length(self, wall: int) -> float:
    return float(self.room[0] if wall in (0, 2) else self.room[1])

  def wall_pose(self, wall: int, t: float, offset: float):
    """World xy and yaw of a point `t` along `wall`, `offset` metres into the room."""
    lx, ly = self.room[0], self.room[1]
    pos, normal = {0: ((t, 0.0), (0.0, 1.0)), 1: ((lx, t), (-1.0, 0.0)),
                   2: ((t, ly), (0.0, -1.0)), 3: ((0.0, t), (1.0, 0.0))}[wall]
    xy = np.array(pos) + offset * np.array(normal)
    return xy, float(np.arctan2(-normal[0], normal[1]))

  def free_on_wall(self, wall: int, width: float, levels, tries: int = 30):
    """A free position along a wall for an item of `width`, or None."""
    length = self.wall_length(wall)
    if width + 0.2 > length:
      return None
    for _ in range(tries):
      t = self.rng.uniform(0.1 + width / 2, length - 0.1 - width / 2)
      lo, hi = t - width / 2 - 0.05, t + width / 2 + 0.05
      if all(hi < a or lo > b for level in levels for a, b in level[wall]):
        for level in levels:
          level[wall].append((lo, hi))
        return t
    return None

  def free_circle(self, x: float, y: float, r: float, ignore: int = -1) -> bool:
    """Whether a footprint circle is inside the room and clear of others (but `ignore`)."""
    lx, ly = self.room[0], self.room[1]
    if x - r < 0.05 or y - r < 0.05 or x + r > lx - 0.05 or y + r > ly - 0.05:
      return False
    return all((x - cx) ** 2 + (y - cy) ** 2 > (r + cr) ** 2
               for cx, cy, cr, owner in self.circles if owner != ignore)

  def add(self, kind: str, label: int, position, yaw: float, size, *, footprint: bool = True):
    size = np.asarray(size, np.float64)
    position = np.asarray(position, np.float64)
    instance = len(self.placements) + 7  # 1..6 are the floor, ceiling and walls
    if footprint:
      self.circles.append((position[0], position[1], 0.5 * np.hypot(size[0], size[1]), instance))
    pl = Placement(kind, label, instance, position, float(yaw), size,
                   self.rng.uniform(size=_NUM_U))
    self.placements.append(pl)
    return pl

  def against_wall(self, kind, label, size, *, wall=None, tall=False, high=False, z=0.0,
                   gap=0.02):
    """Places an item against a wall; returns the placement or None if none fits."""
    walls = [wall] if wall is not None else list(self.rng.permutation(4))
    levels = ([self.wall_low, self.wall_high] if tall else
              [self.wall_high] if high else [self.wall_low])
    for w in walls:
      t = self.free_on_wall(int(w), size[0], levels)
      if t is not None:
        xy, yaw = self.wall_pose(int(w), t, size[1] / 2 + gap)
        return self.add(kind, label, (xy[0], xy[1], z), yaw, size, footprint=not high)
    return None

  def in_room(self, kind, label, size, *, margin=1.0, tries=60, yaw=None):
    """Places an item in the free interior; returns the placement or None."""
    r = 0.5 * np.hypot(size[0], size[1])
    lx, ly = self.room[0], self.room[1]
    for _ in range(tries):
      x = self.rng.uniform(margin + r, lx - margin - r) if lx > 2 * (margin + r) else lx / 2
      y = self.rng.uniform(margin + r, ly - margin - r) if ly > 2 * (margin + r) else ly / 2
      if self.free_circle(x, y, r):
        a = yaw if yaw is not None else self.rng.choice([0, 0.5, 1, 1.5]) * np.pi
        a += self.rng.normal(0, 0.05)
        return self.add(kind, label, (x, y, 0.0), a, size)
    return None

  def on_top(self, base: Placement, kind, label, size, rel_xy):
    """Places an item on top of `base` at `rel_xy` in the base's frame."""
    top = base.position[2] + base.size[2]
    rel_xy = np.asarray(rel_xy, np.float64)
    if base.kind == "table":  # stay inside the ellipse inscribed in the top (round tops)
      r = np.sum(np.square(rel_xy / (base.size[:2] / 2)))
      rel_xy = rel_xy * np.sqrt(min(1.0, 0.7 / max(r, 1e-9)))
    xy = base.position[:2] + rot_z(base.yaw)[:2, :2] @ rel_xy
    return self.add(kind, label, (xy[0], xy[1], top), base.yaw + self.rng.normal(0, 0.15), size,
                    footprint=False)

  def beside(self, base: Placement, kind, label, size, rel_xy, rel_yaw):
    """Places a floor item relative to `base` if its footprint is free (`base` aside)."""
    xy = base.position[:2] + rot_z(base.yaw)[:2, :2] @ np.asarray(rel_xy, np.float64)
    r = 0.5 * np.hypot(size[0], size[1])
    if not self.free_circle(xy[0], xy[1], r * 0.8, ignore=base.instance):
      return None
    return self.add(kind, label, (xy[0], xy[1], 0.0), base.yaw + rel_yaw + self.rng.normal(0, 0.08),
                    size)


def _structure(plan: _Planner, env: str):
  """Doors, windows, ceiling panels, pictures."""
  rng = plan.rng
  room = plan.room
  for _ in range(1 + int(rng.uniform() < 0.6)):
    plan.against_wall("door", BACKGROUND, (rng.uniform(0.85, 1.0), 0.05, rng.uniform(2.0, 2.15)),
                      tall=True, gap=0.0)
  for _ in range(2 + int(rng.uniform() < 0.5)):
    w = rng.uniform(1.0, 1.6)
    plan.against_wall("window", BACKGROUND, (w, 0.04, rng.uniform(1.0, 1.3)), high=True,
                      z=rng.uniform(0.85, 1.0), gap=0.0)
  n_panels = 4 if env == "office" else 1
  for i in range(n_panels):
    x = room[0] * ((i % 2) + 0.5) / 2 if n_panels > 1 else room[0] / 2
    y = room[1] * ((i // 2) + 0.5) / 2 if n_panels > 1 else room[1] / 2
    plan.add("light_panel", BACKGROUND, (x, y, room[2]), 0.0, (1.2, 0.6, 0.02), footprint=False)
  for _ in range(1 + int(rng.uniform() < 0.7)):
    plan.against_wall("picture", BACKGROUND,
                      (rng.uniform(0.5, 1.0), 0.03, rng.uniform(0.4, 0.7)), high=True,
                      z=rng.uniform(1.2, 1.5), gap=0.0)
  if env == "office":
    plan.against_wall("whiteboard", BACKGROUND, (rng.uniform(1.4, 2.0), 0.03, 1.0), high=True,
                      z=0.95, gap=0.0)


def _clutter(plan: _Planner, env: str):
  rng = plan.rng
  for _ in range(2 if env == "office" else 1 + int(rng.uniform() < 0.6)):
    plan.against_wall("shelf", BACKGROUND, (rng.uniform(0.8, 1.2), 0.35, rng.uniform(1.5, 1.85)),
                      tall=True)
  for _ in range(1 + int(rng.uniform() < 0.5)):
    plan.against_wall("cabinet", BACKGROUND, (rng.uniform(0.8, 1.4), 0.45, rng.uniform(0.6, 0.9)))
  for _ in range(2 + int(rng.uniform() < 0.5)):
    e = rng.uniform(0.3, 0.55)
    plan.against_wall("box", BACKGROUND, (e, e * rng.uniform(0.7, 1.0), e * rng.uniform(0.6, 1.0)))
  for _ in range(1 + int(env == "house")):
    plan.against_wall("floor_lamp", BACKGROUND, (0.4, 0.4, rng.uniform(1.4, 1.65)), tall=True,
                      gap=0.1)
  plan.in_room("stool", BACKGROUND, (0.36, 0.36, rng.uniform(0.45, 0.65)), margin=1.0)


def _office(plan: _Planner):
  rng = plan.rng
  room = plan.room
  desks = []
  n_desks = int(rng.integers(4, 6))
  for _ in range(n_desks):
    w, d = rng.uniform(1.2, 1.6), rng.uniform(0.7, 0.8)
    desk = plan.in_room("table", TABLE, (w, d, 0.75), margin=1.2, yaw=rng.choice([0.0, np.pi]))
    if desk is None:
      continue
    desks.append(desk)
    # The chair is on the desk's +y side, facing the desk.
    plan.beside(desk, "chair", CHAIR, (0.5, 0.5, 0.0), (rng.uniform(-0.2, 0.2), d / 2 + 0.35),
                np.pi)
    if rng.uniform() < 0.85:
      plan.on_top(desk, "tv", TV, (rng.uniform(0.5, 0.7), 0.2, 0.0), (rng.uniform(-0.2, 0.2),
                                                                        -d / 2 + 0.18))
    for _ in range(int(rng.integers(0, 3))):
      plan.on_top(desk, "bottle", BOTTLE, (0.08, 0.08, 0.0),
                  (rng.choice([-1, 1]) * rng.uniform(0.35, w / 2 - 0.08), rng.uniform(-0.2, 0.25)))
    if rng.uniform() < 0.3:
      plan.on_top(desk, "plant", PLANT, (0.2, 0.2, 0.35), (rng.choice([-1, 1]) * (w / 2 - 0.15),
                                                           -d / 2 + 0.15))
    if rng.uniform() < 0.3:
      plan.on_top(desk, "box", BACKGROUND, (0.3, 0.22, 0.1), (rng.uniform(-0.3, 0.3), 0.1))
    if rng.uniform() < 0.5:
      plan.beside(desk, "trash_bin", BACKGROUND, (0.3, 0.3, 0.35),
                  (rng.choice([-1, 1]) * (w / 2 + 0.25), 0.1), 0.0)
  for _ in range(1 + int(rng.uniform() < 0.5)):
    sofa = plan.against_wall("sofa", SOFA, (rng.uniform(1.6, 2.1), 0.9, 0.0))
    if sofa is not None and rng.uniform() < 0.7:
      table = plan.beside(sofa, "table", TABLE, (1.0, 0.55, 0.42), (0.0, 1.0), 0.0)
      if table is not None:
        plan.on_top(table, "bottle", BOTTLE, (0.08, 0.08, 0.0), (rng.uniform(-0.3, 0.3), 0.0))
  for _ in range(int(rng.integers(2, 4))):
    plan.against_wall("plant", PLANT, (0.55, 0.55, 1.0), gap=0.08)
  if rng.uniform() < 0.6:
    cab = plan.against_wall("cabinet", BACKGROUND, (1.0, 0.45, 0.75))
    if cab is not None:
      plan.on_top(cab, "tv", TV, (rng.uniform(0.8, 1.0), 0.2, 0.0), (0.0, 0.0))
      plan.on_top(cab, "vase", BACKGROUND, (0.15, 0.15, 0.2), (0.4, 0.05))


def _house(plan: _Planner):
  rng = plan.rng
  wall = int(rng.integers(0, 4))
  sofa = plan.against_wall("sofa", SOFA, (rng.uniform(1.8, 2.2), 0.92, 0.0), wall=wall)
  if sofa is None:
    sofa = plan.against_wall("sofa", SOFA, (1.7, 0.9, 0.0))
  cab = plan.against_wall("cabinet", BACKGROUND, (rng.uniform(1.3, 1.7), 0.45, 0.55),
                          wall=(wall + 2) % 4)
  if cab is not None:
    plan.on_top(cab, "tv", TV, (rng.uniform(0.9, 1.2), 0.2, 0.0), (0.0, 0.0))
    plan.on_top(cab, "vase", BACKGROUND, (0.15, 0.15, 0.2), (rng.choice([-1, 1]) * 0.6, 0.05))
  if rng.uniform() < 0.6:
    plan.against_wall("sofa", SOFA, (rng.uniform(1.4, 1.8), 0.88, 0.0), wall=(wall + 1) % 4)
  if sofa is not None:
    coffee = plan.beside(sofa, "table", TABLE, (1.1, 0.6, 0.42), (0.0, 1.05), 0.0)
    if coffee is not None:
      plan.add("rug", BACKGROUND, coffee.position, coffee.yaw, (2.2, 1.6, 0.0), footprint=False)
      for _ in range(int(rng.integers(1, 3))):
        plan.on_top(coffee, "bottle", BOTTLE, (0.08, 0.08, 0.0),
                    (rng.uniform(-0.4, 0.4), rng.uniform(-0.15, 0.15)))
      for sx in (-1, 1):
        if rng.uniform() < 0.75:
          plan.beside(coffee, "chair", CHAIR, (0.7, 0.7, 0.0), (sx * 1.05, 0.0), -sx * np.pi / 2)
  w, d = rng.uniform(1.4, 1.8), rng.uniform(0.8, 0.95)
  dining = plan.in_room("table", TABLE, (w, d, 0.75), margin=1.0)
  if dining is not None:
    for sx in (-0.25, 0.25):
      for sy in (-1, 1):
        if rng.uniform() < 0.9:
          yaw = np.pi if sy > 0 else 0.0
          plan.beside(dining, "chair", CHAIR, (0.46, 0.46, 0.0), (sx * w, sy * (d / 2 + 0.3)), yaw)
    for _ in range(int(rng.integers(2, 5))):
      plan.on_top(dining, "bottle", BOTTLE, (0.08, 0.08, 0.0),
                  (rng.uniform(-w / 2 + 0.15, w / 2 - 0.15), rng.uniform(-0.2, 0.2)))
    if rng.uniform() < 0.6:
      plan.on_top(dining, "plant", PLANT, (0.2, 0.2, 0.35), (0.0, 0.0))
  side = plan.against_wall("table", TABLE, (0.55, 0.55, 0.55))
  if side is not None:
    if rng.uniform() < 0.6:
      plan.on_top(side, "bottle", BOTTLE, (0.08, 0.08, 0.0), (0.0, 0.0))
    else:
      plan.on_top(side, "plant", PLANT, (0.2, 0.2, 0.35), (0.0, 0.0))
  if rng.uniform() < 0.9:
    desk = plan.against_wall("table", TABLE, (1.1, 0.6, 0.75))
    if desk is not None:
      plan.on_top(desk, "tv", TV, (0.55, 0.2, 0.0), (0.0, -0.12))
      plan.beside(desk, "chair", CHAIR, (0.46, 0.46, 0.0), (0.0, 0.6), np.pi)
  for _ in range(int(rng.integers(2, 4))):
    plan.against_wall("plant", PLANT, (0.55, 0.55, 1.0), gap=0.08)


def make_layout(env: str, seed: int) -> Layout:
  """Draws a room layout.

  Args:
    env: "office" (desks with chairs and monitors, a waiting sofa, shelves, whiteboard) or
      "house" (living area with sofa, coffee table, TV, armchairs; a dining table with chairs).
    seed: any non-negative integer; the layout is a pure function of `(env, seed)`.

  Returns:
    A `Layout`.
  """
  if env not in ENVIRONMENTS:
    raise ValueError(f"unknown environment {env!r}; expected one of {ENVIRONMENTS}")
  rng = np.random.default_rng([int(seed), ENVIRONMENTS.index(env), 7193])
  if env == "office":
    room = np.array([rng.uniform(7.5, 9.0), rng.uniform(6.0, 7.2), rng.uniform(2.8, 3.0)])
  else:
    room = np.array([rng.uniform(6.2, 7.5), rng.uniform(5.4, 6.5), rng.uniform(2.5, 2.7)])
  plan = _Planner(rng, room)
  _structure(plan, env)
  (_office if env == "office" else _house)(plan)
  _clutter(plan, env)
  return Layout(env, int(seed), room, tuple(plan.placements), rng.uniform(size=4))


def build_primitives(layout: Layout, s: float) -> Primitives:
  """The primitive table of a layout in a domain.

  Args:
    layout: output of `make_layout`.
    s: domain weight (0 = train, 1 = full test domain; see `appearance.domain_shift`).

  Returns:
    `Primitives`: the room (floor, ceiling and four walls as planes; instance ids 1..6) and
    every placed object.
  """
  lx, ly, h = layout.room
  rng = np.random.default_rng([layout.seed, ENVIRONMENTS.index(layout.env), 31])
  u_struct = rng.uniform(size=(3, 4))
  floor = appearance.material("floor", u_struct[0], s)
  wall = appearance.material("wall", u_struct[1], s)
  ceiling = appearance.material("ceiling", u_struct[2], s)
  placed = [
      (part(PLANE, (lx / 2, ly / 2, 0.0), (1, 1, 1), floor), BACKGROUND, 1),
      (part(PLANE, (lx / 2, ly / 2, h), (1, 1, 1), ceiling), BACKGROUND, 2),
  ]
  for i, (c, yaw) in enumerate((((lx / 2, 0.0), 0.0), ((lx, ly / 2), np.pi / 2),
                                ((lx / 2, ly), np.pi), ((0.0, ly / 2), -np.pi / 2))):
    wall_plane = part(PLANE, (c[0], c[1], h / 2), (1, 1, 1), wall,
                      rotation=rot_z(yaw) @ rot_x(np.pi / 2))
    placed.append((wall_plane, BACKGROUND, 3 + i))
  for pl in layout.placements:
    placed += place(BUILDERS[pl.kind](pl, s), pl.position, pl.yaw, pl.label, pl.instance)
  return to_table(placed)
