"""A building-sized embedded world: a floor of N furnished rooms joined by corridors.

`make_floor(num_rooms, seed=...)` lays out N rooms of the embedded world (`scene.make_layout`,
office or house, their furniture built by `scene.BUILDERS`, so the classes are `CLASS_NAMES`)
along corridors, and `FloorWalk` walks a camera through every corridor and every room,
rendering its frames with the embedded renderer (`synthetic.render`) one at a time, so that a
walk of thousands of frames never has to be held whole.

The plan. Rooms stand in *bands*: a straight corridor (2.2 m wide) with rooms on both sides, at
most 8 rooms a band; several bands are joined by a spine corridor along their west ends. Every
room keeps its own layout (size, furniture) and is turned by a multiple of 90° so that the door
its layout drew faces the corridor; that door becomes an open doorway (2.0–2.15 m high) through
the room's wall and the corridor's. Walls are boxes, 0.12 m thick (each cell owns the half on
its side, so no two visible faces coincide); one floor plane and one ceiling plane (2.8 m) span
the building. Cells (rooms and corridors) are axis-aligned rectangles in the floor's frame
(x east, y north, z up); the world frame of the poses is the floor's frame moved by
`synthetic.placement("office", seed)` (a turn of 5–15° and tilts of 1–3°), so that no wall lies
on a voxel grid, as in the embedded sequences.

The walk. From the west end of the first corridor the camera walks each corridor east, turning
into each room it passes: through the doorway, once around the room 1.1 m inside its walls,
and out again; at the end of a band it walks back to the spine and on to the next band. The
path is a polyline smoothed with a Gaussian (σ = 0.25 m) and sampled every `STEP` metres at eye
height (1.45–1.6 m, above the furniture that stands away from the walls); the view looks ahead,
turned towards the room's centre inside a room, panning ±0.5 rad as it goes, 18° below the
horizon. A walk of 12 rooms is about 0.4 km: ~4,000 frames.

Rendering. The sensor has a range of `MAX_RANGE` metres: a pixel whose hit lies farther reads
no depth (0, label 0), and primitives whose bounding sphere lies wholly beyond it are left out
of the frame's tile lists (`raycast.tile_lists(candidates=...)`), so a frame costs about what a
frame of one room costs, whatever the size of the floor. Each frame is lit by the lamp of the
cell the camera is in. With `realism`, depth gets the embedded sensor noise and colour the camera
model of `SensingConfig` with a settled auto-exposure per frame (`synthetic.render`'s default
camera state); labels stay exact.

Shape legend: T frames, H×W pixels, P primitives, C cells.
"""

from typing import Iterator, NamedTuple, Optional

import jax
import numpy as np

from jaxfusion.camera import Camera
from jaxfusion.datasets import appearance, scene, synthetic
from jaxfusion.datasets.classes import BACKGROUND, CLASS_NAMES
from jaxfusion.datasets.primitives import BOX, PLANE, part, place, rot_z, to_table
from jaxfusion.datasets.sequence import RGBDFrame, RGBDSequence
from jaxfusion.datasets.trajectories import look_at

HEIGHT = 2.8          # floor-to-ceiling height of every cell (metres)
WALL = 0.12           # wall thickness (each cell owns half of it)
CORRIDOR = 2.2        # corridor width
ROOMS_PER_BAND = 8    # rooms on the two sides of one corridor, at most
INSET = 1.1           # the walk's loop inside a room, from its walls
STEP = 0.1            # metres walked between frames
MAX_RANGE = 8.0       # sensor range (metres along the ray)
MAX_ROOMS = 100
# Per-tile candidate list lengths every frame is padded to (one compilation for most frames).
TILE_SIZES = (32, 32, 16, 8)
_SIGMA = 0.25         # path smoothing (metres)
_PAN = 0.5            # view pan amplitude (radians)
_SEED_BASE = 500_000  # room layout seeds: disjoint from the sequences' and the training views'


class Cell(NamedTuple):
  """A room or a corridor: an axis-aligned rectangle of floor.

  Attributes:
    kind: "room" or "corridor".
    lo: `(2,) float64` interior minimum corner (x, y).
    hi: `(2,) float64` interior maximum corner.
  """
  kind: str
  lo: np.ndarray
  hi: np.ndarray

  @property
  def centre(self) -> np.ndarray:
    return (self.lo + self.hi) / 2


class Opening(NamedTuple):
  """A passage between two cells through the wall between them.

  Attributes:
    cells: `(a, b)` cell indices.
    axis: 0 for a wall at constant x, 1 for a wall at constant y.
    at: the wall's mid-line coordinate along `axis`.
    lo: start of the passage along the wall.
    hi: end of the passage along the wall.
    height: its height (`HEIGHT`: no lintel).
  """
  cells: tuple
  axis: int
  at: float
  lo: float
  hi: float
  height: float


class Floor(NamedTuple):
  """A floor of rooms in one appearance domain.

  Attributes:
    num_rooms: N.
    seed: the layout seed it was drawn from.
    cells: tuple of C `Cell`s, the N rooms first, then the corridors.
    openings: tuple of `Opening`s (one doorway per room, one per band's end on the spine).
    room_layouts: the N rooms' `scene.Layout`s, in their own frames.
    T_floor_room: `(N, 4, 4) float64` where each room's frame sits in the floor's.
    world: the `synthetic.SyntheticScene` of the whole floor (its `layout.placements` in the
      floor's frame; `lighting` that of the first room).
    lightings: C `appearance.Lighting`s, one per cell (corridors: see `lighting_at`).
    T_world_floor: `(4, 4) float64` where the floor sits in the world frame of the poses.
  """
  num_rooms: int
  seed: int
  cells: tuple
  openings: tuple
  room_layouts: tuple
  T_floor_room: np.ndarray
  world: synthetic.SyntheticScene
  lightings: tuple
  T_world_floor: np.ndarray


# ------------------------------------------------------------------------------- the plan


def _door(layout: scene.Layout):
  """`(placement or None, wall index, position along the wall, width, height)` of the door the
  room's layout drew first (the room's doorway), or a made-up one mid-wall 0."""
  lx, ly = layout.room[:2]
  for pl in layout.placements:
    if pl.kind == "door":
      x, y = pl.position[:2]
      wall = int(np.argmin([y, lx - x, ly - y, x]))
      along = x if wall in (0, 2) else y
      return pl, wall, float(along), float(pl.size[0]), float(pl.size[2])
  return None, 0, float(lx / 2), 0.9, 2.05


def _turned(layout: scene.Layout, quarter_turns: int, lo) -> np.ndarray:
  """`(4, 4)` T_floor_room: the room turned by `quarter_turns` · 90°, its footprint's minimum
  corner at `lo (2,)`."""
  lx, ly = layout.room[:2]
  R = np.round(rot_z(quarter_turns * np.pi / 2))
  corners = np.array([[0, 0, 0], [lx, 0, 0], [0, ly, 0], [lx, ly, 0]]) @ R.T
  T = np.eye(4)
  T[:3, :3] = R
  T[:2, 3] = np.asarray(lo, np.float64) - corners[:, :2].min(0)
  return T


def _footprint(layout: scene.Layout, quarter_turns: int) -> np.ndarray:
  lx, ly = layout.room[:2]
  return np.array([lx, ly] if quarter_turns % 2 == 0 else [ly, lx])


def _plan(num_rooms: int, seed: int):
  """Draws the rooms and lays them out; returns `(cells, openings, layouts, T_floor_room,
  bands)` where `bands` lists per band `(corridor cell, [room cells in walking order])`."""
  rng = np.random.default_rng([int(seed), num_rooms, 8181])
  layouts = [scene.make_layout(scene.ENVIRONMENTS[int(rng.integers(2))],
                               _SEED_BASE + 1000 * int(seed) + i) for i in range(num_rooms)]
  num_bands = -(-num_rooms // ROOMS_PER_BAND)
  per_band = [len(b) for b in np.array_split(np.arange(num_rooms), num_bands)]
  cells, openings, transforms, bands = [None] * num_rooms, [], [None] * num_rooms, []
  corridors = []
  y_cursor, index = 0.0, 0
  for count in per_band:
    members = list(range(index, index + count))
    index += count
    south, north = members[0::2], members[1::2]
    # Quarter turns that bring each room's door to the corridor side (south rooms: +y).
    turns = {}
    for i in members:
      _, wall, _, _, _ = _door(layouts[i])
      turns[i] = ((2 if i in south else 0) - wall) % 4
    depth_s = max(_footprint(layouts[i], turns[i])[1] for i in south)
    depth_n = max([_footprint(layouts[i], turns[i])[1] for i in north] or [0.0])
    y_corr = y_cursor + depth_s + WALL                      # corridor's south interior edge
    lengths = []
    for side, rooms in (("south", south), ("north", north)):
      x = 0.0
      for i in rooms:
        w, d = _footprint(layouts[i], turns[i])
        y0 = y_corr - WALL - d if side == "south" else y_corr + CORRIDOR + WALL
        transforms[i] = _turned(layouts[i], turns[i], (x, y0))
        cells[i] = Cell("room", np.array([x, y0]), np.array([x + w, y0 + d]))
        x += w + WALL
      lengths.append(x - WALL)
    corridor = Cell("corridor", np.array([0.0, y_corr]),
                    np.array([max(lengths), y_corr + CORRIDOR]))
    corridors.append(corridor)
    bands.append((len(corridors) - 1, members))
    y_cursor = y_corr + CORRIDOR + WALL + (depth_n + WALL if north else 0.0)
  num_cells = num_rooms + len(corridors)
  cells = cells + corridors
  for b, (c, members) in enumerate(bands):
    for i in members:
      pl, wall, along, width, height = _door(layouts[i])
      T = transforms[i]
      local = np.array([[along, 0.0], [layouts[i].room[0], along], [along, layouts[i].room[1]],
                        [0.0, along]][wall])
      x = float((T[:2, :2] @ local + T[:2, 3])[0])
      south = cells[i].hi[1] < cells[num_rooms + c].lo[1]
      at = cells[num_rooms + c].lo[1] - WALL / 2 if south else cells[num_rooms + c].hi[1] + WALL / 2
      openings.append(Opening((i, num_rooms + c), 1, float(at), x - width / 2, x + width / 2,
                              height))
  if len(corridors) > 1:                                    # the spine along the west ends
    spine = Cell("corridor", np.array([-WALL - CORRIDOR, corridors[0].lo[1]]),
                 np.array([-WALL, corridors[-1].hi[1]]))
    cells.append(spine)
    for c, corridor in enumerate(corridors):
      openings.append(Opening((num_rooms + c, num_cells), 0, -WALL / 2, float(corridor.lo[1]),
                              float(corridor.hi[1]), HEIGHT))
  bands = [(num_rooms + c, members) for c, members in bands]
  return tuple(cells), tuple(openings), tuple(layouts), np.stack(transforms), bands


def _walls(cells, openings, materials) -> list:
  """`(Part, label, instance)` boxes of every cell's half-walls, cut at the openings."""
  placed, instance = [], 3
  half = WALL / 2
  for c, cell in enumerate(cells):
    for side in range(4):                  # 0: y = lo, 1: x = hi, 2: y = hi, 3: x = lo
      axis = 1 if side in (0, 2) else 0    # the wall's normal axis
      along = 1 - axis
      inner = cell.lo[axis] if side in (0, 3) else cell.hi[axis]
      outer = inner - half if side in (0, 3) else inner + half
      at = inner - WALL / 2 if side in (0, 3) else inner + WALL / 2
      start, stop = cell.lo[along] - half, cell.hi[along] + half
      cuts = sorted((o.lo, o.hi, o.height) for o in openings
                    if c in o.cells and o.axis == axis and abs(o.at - at) < 1e-6)
      pieces, cursor = [], start
      for lo, hi, height in cuts:
        pieces.append((cursor, lo, 0.0, HEIGHT))
        if height < HEIGHT:
          pieces.append((lo, hi, height, HEIGHT))
        cursor = hi
      pieces.append((cursor, stop, 0.0, HEIGHT))
      for a, b, z0, z1 in pieces:
        if b - a < 1e-6:
          continue
        centre, size = np.zeros(3), np.zeros(3)
        centre[along], size[along] = (a + b) / 2, (b - a) / 2
        centre[axis], size[axis] = (inner + outer) / 2, half / 2
        centre[2], size[2] = (z0 + z1) / 2, (z1 - z0) / 2
        placed.append((part(BOX, centre, size, materials[c]), BACKGROUND, instance))
      instance += 1
  return placed


def make_floor(num_rooms: int, *, seed: int = 0, domain: str = "test",
               shift: float = 1.0) -> Floor:
  """Builds a floor of `num_rooms` furnished rooms joined by corridors.

  Args:
    num_rooms: N in [1, `MAX_ROOMS`].
    seed: layout seed: the rooms (their environment, size and furniture), their order and
      the floor's placement depend on `(num_rooms, seed)` only.
    domain: "train" or "test" appearance.
    shift: strength of the "test" domain gap in [0, 1].

  Returns:
    A `Floor`.
  """
  if isinstance(num_rooms, bool) or not isinstance(num_rooms, (int, np.integer)) or not (
      1 <= num_rooms <= MAX_ROOMS):
    raise ValueError(f"a floor has 1 to {MAX_ROOMS} rooms; got {num_rooms!r}")
  if int(seed) < 0:
    raise ValueError(f"seed must be ≥ 0; got {seed}")
  s = appearance.domain_shift(domain, shift)
  num_rooms = int(num_rooms)
  cells, openings, layouts, transforms, _ = _plan(num_rooms, int(seed))
  rng = np.random.default_rng([int(seed), num_rooms, 31])
  u_struct = rng.uniform(size=(2 + len(cells), 4))
  placed = [(part(PLANE, (0.0, 0.0, 0.0), (1, 1, 1), appearance.material("floor", u_struct[0], s)),
             BACKGROUND, 1),
            (part(PLANE, (0.0, 0.0, HEIGHT), (1, 1, 1),
                  appearance.material("ceiling", u_struct[1], s)), BACKGROUND, 2)]
  placed += _walls(cells, openings, [appearance.material("wall", u, s) for u in u_struct[2:]])
  instance = max(i for _, _, i in placed) + 1
  everything, lightings = [], []
  for layout, T in zip(layouts, transforms):
    doorway = _door(layout)[0]
    yaw = float(np.arctan2(T[1, 0], T[0, 0]))
    for pl in layout.placements:
      if doorway is not None and pl.instance == doorway.instance:
        continue                            # the doorway: an opening, not a closed door
      position = T[:3, :3] @ pl.position + T[:3, 3]
      if pl.kind == "light_panel":
        position[2] = HEIGHT
      moved = pl._replace(position=position, yaw=pl.yaw + yaw, instance=instance)
      instance += 1
      everything.append(moved)
      placed += place(scene.BUILDERS[pl.kind](pl, s), position, moved.yaw, pl.label,
                      moved.instance)
    light = appearance.lighting(np.array([*layout.room[:2], HEIGHT]), layout.light_u, s)
    lightings.append(light._replace(lamp_pos=np.asarray(
        T[:3, :3] @ light.lamp_pos + T[:3, 3], np.float32)))
  for c in range(num_rooms, len(cells)):
    size = np.array([*(cells[c].hi - cells[c].lo), HEIGHT])
    light = appearance.lighting(size, rng.uniform(size=4), s)
    lightings.append(light._replace(lamp_pos=np.asarray(
        light.lamp_pos + np.array([*cells[c].lo, 0.0]), np.float32)))
  extent = np.array([*(max(c.hi[0] for c in cells) - min(c.lo[0] for c in cells),
                       max(c.hi[1] for c in cells) - min(c.lo[1] for c in cells)), HEIGHT])
  layout = scene.Layout("floor", int(seed), extent, tuple(everything), layouts[0].light_u)
  world = synthetic.SyntheticScene(layout, to_table(placed), lightings[0], domain, float(shift))
  return Floor(num_rooms, int(seed), cells, openings, layouts, transforms, world,
               tuple(lightings), synthetic.placement("office", int(seed)))


def connected(floor: Floor) -> bool:
  """Whether every cell can be reached from every other through the openings."""
  reach, frontier = {0}, [0]
  while frontier:
    c = frontier.pop()
    for o in floor.openings:
      if c in o.cells:
        other = o.cells[1] if o.cells[0] == c else o.cells[0]
        if other not in reach:
          reach.add(other)
          frontier.append(other)
  return len(reach) == len(floor.cells)


def cell_of(floor: Floor, xy) -> np.ndarray:
  """`(N,) int` the cell whose interior holds each floor-frame point `xy (N, 2)` (-1: none,
  e.g. in a doorway or inside a wall)."""
  xy = np.asarray(xy, np.float64).reshape(-1, 2)
  out = np.full(len(xy), -1)
  for c, cell in enumerate(floor.cells):
    inside = np.all((xy >= cell.lo) & (xy <= cell.hi), axis=1)
    out = np.where((out < 0) & inside, c, out)
  return out


def in_free_space(floor: Floor, xy, *, margin: float = 0.2) -> np.ndarray:
  """`(N,) bool`: each floor-frame point lies at least `margin` inside a cell's interior, or
  in a doorway at least `margin` from its jambs — never inside a wall."""
  xy = np.asarray(xy, np.float64).reshape(-1, 2)
  free = np.zeros(len(xy), bool)
  for cell in floor.cells:
    free |= np.all((xy >= cell.lo + margin) & (xy <= cell.hi - margin), axis=1)
  for o in floor.openings:
    along = xy[:, 1 - o.axis]
    across = np.abs(xy[:, o.axis] - o.at)
    free |= (along >= o.lo + margin) & (along <= o.hi - margin) & (across <= WALL / 2 + margin)
  return free


# ------------------------------------------------------------------------------- the walk


def _waypoints(floor: Floor) -> np.ndarray:
  """`(M, 2)` the walk's polyline in the floor's frame (see the module docstring)."""
  _, _, _, _, bands = _plan(floor.num_rooms, floor.seed)
  doors = {o.cells[0]: o for o in floor.openings if o.cells[0] < floor.num_rooms}
  points = []
  spine_x = -WALL - CORRIDOR / 2
  for b, (c, members) in enumerate(bands):
    corridor = floor.cells[c]
    y_mid = float(corridor.centre[1])
    if b:                                                   # arrived along the spine
      points.append((spine_x, y_mid))
    points.append((corridor.lo[0] + INSET, y_mid))
    for i in sorted(members, key=lambda i: (doors[i].lo + doors[i].hi) / 2):
      door, room = doors[i], floor.cells[i]
      x = (door.lo + door.hi) / 2
      south = room.hi[1] < corridor.lo[1]
      y_in = room.hi[1] - INSET if south else room.lo[1] + INSET
      x_lo, x_hi = room.lo[0] + INSET, room.hi[0] - INSET
      y_far = room.lo[1] + INSET if south else room.hi[1] - INSET
      x_in = float(np.clip(x, x_lo, x_hi))
      points += [(x, y_mid), (x, door.at), (x_in, y_in)]
      points += [(x_hi, y_in), (x_hi, y_far), (x_lo, y_far), (x_lo, y_in), (x_in, y_in)]
      points += [(x, door.at), (x, y_mid)]
    points.append((corridor.hi[0] - INSET, y_mid))
    if b + 1 < len(bands):                                   # back to the spine
      points += [(corridor.lo[0] + INSET, y_mid), (spine_x, y_mid)]
  return np.asarray(points, np.float64)


def _resample(points: np.ndarray, spacing: float) -> np.ndarray:
  """Points every `spacing` metres along a polyline `(M, 2)`."""
  seg = np.linalg.norm(np.diff(points, axis=0), axis=1)
  keep = np.concatenate([[True], seg > 1e-9])
  points = points[keep]
  s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
  at = np.arange(0.0, s[-1] + 1e-9, spacing)
  return np.stack([np.interp(at, s, points[:, k]) for k in range(2)], -1)


def _smooth(x: np.ndarray, sigma: float) -> np.ndarray:
  """Gaussian smoothing along the first axis (`sigma` in samples, edges held)."""
  radius = max(1, int(3 * sigma))
  w = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
  w /= w.sum()
  padded = np.concatenate([np.repeat(x[:1], radius, 0), x, np.repeat(x[-1:], radius, 0)])
  return np.stack([np.convolve(padded[:, k], w, mode="valid") for k in range(x.shape[1])], -1)


def walk_poses(floor: Floor) -> np.ndarray:
  """The floor's whole walk, one pose every `STEP` metres.

  Args:
    floor: output of `make_floor`.

  Returns:
    `(T, 4, 4) float32` camera-to-floor poses (the world's are `T_world_floor @` these).
  """
  fine = 0.02
  path = _smooth(_resample(_waypoints(floor), fine), _SIGMA / fine)
  path = _resample(path, STEP)
  n = len(path)
  ahead = np.gradient(path, axis=0)
  ahead /= np.maximum(np.linalg.norm(ahead, axis=1, keepdims=True), 1e-9)
  cell = cell_of(floor, path)
  for t in range(n):                        # doorways: the cell of the nearest sample in one
    if cell[t] < 0:
      near = np.nonzero(cell >= 0)[0]
      cell[t] = cell[near[np.argmin(np.abs(near - t))]] if len(near) else 0
  centres = np.array([floor.cells[c].centre for c in cell])
  inward = centres - path
  inward /= np.maximum(np.linalg.norm(inward, axis=1, keepdims=True), 0.3)
  in_room = (cell < floor.num_rooms)[:, None]
  gaze = ahead + np.where(in_room, 1.5 * inward, 0.0)
  s = np.arange(n) * STEP
  yaw = np.unwrap(np.arctan2(gaze[:, 1], gaze[:, 0])) + _PAN * np.sin(2 * np.pi * s / 7.0)
  yaw = _smooth(yaw[:, None], 0.6 / STEP)[:, 0]
  eye_z = 1.45 + 0.15 * (1 + np.sin(2 * np.pi * s / 11.0)) / 2
  target = np.stack([path[:, 0] + 2.5 * np.cos(yaw), path[:, 1] + 2.5 * np.sin(yaw),
                     eye_z - 0.8], -1)
  eye = np.concatenate([path, eye_z[:, None]], -1)
  return np.stack([look_at(e, g) for e, g in zip(eye, target)])


class FloorWalk:
  """The frames of a walk through a floor, rendered when asked for.

  Attributes:
    floor: the `Floor`.
    camera: intrinsics (`synthetic.default_camera`).
    T_floor_cam: `(T, 4, 4) float32` the frames' poses in the floor's frame.
    T_world_cam: `(T, 4, 4) float32` the poses the frames report (world frame).
    name: `f"floor_{N}_{domain}"`.
    walk_frames: frames of the whole walk (before `stride` and `num_frames`).
  """

  def __init__(self, floor: Floor, *, num_frames: Optional[int] = None, stride: int = 1,
               height: int = 120, width: int = 160, realism: bool = True, sensing=None):
    if height < 1 or width < 1:
      raise ValueError(f"image size must be positive; got {height}x{width}")
    if int(stride) < 1:
      raise ValueError(f"stride must be ≥ 1; got {stride}")
    if num_frames is not None and int(num_frames) < 1:
      raise ValueError(f"num_frames must be ≥ 1; got {num_frames}")
    self.floor = floor
    self.height, self.width = int(height), int(width)
    self.realism, self.sensing = bool(realism), sensing
    self.camera = synthetic.default_camera(self.height, self.width)
    whole = walk_poses(floor)
    self.walk_frames = len(whole)
    self.T_floor_cam = whole[::int(stride)][:num_frames]
    self.T_world_cam = np.einsum("ij,tjk->tik", floor.T_world_floor,
                                 self.T_floor_cam).astype(np.float32)
    self.name = f"floor_{floor.num_rooms}_{floor.world.domain}"
    prims = floor.world.primitives
    self._centre = prims.center.astype(np.float64)
    self._radius = np.linalg.norm(prims.half_size.astype(np.float64), axis=1)
    self._plane = prims.kind == PLANE
    self._cell = cell_of(floor, self.T_floor_cam[:, :2, 3])
    d = np.stack(np.meshgrid((np.arange(self.width) - self.camera.cx) / self.camera.fx,
                             (np.arange(self.height) - self.camera.cy) / self.camera.fy), -1)
    self._ray_scale = np.sqrt(1.0 + np.sum(d * d, -1)).astype(np.float32)   # range / z-depth

  def __len__(self) -> int:
    return len(self.T_floor_cam)

  def lighting_at(self, t: int) -> appearance.Lighting:
    """The lighting of frame t: its cell's (a corridor's lamp moves along with the camera, over
    the nearest 4 m mark; a doorway keeps the previous frame's cell)."""
    cells = self._cell[:t + 1]
    seen = cells[cells >= 0]
    c = int(seen[-1]) if len(seen) else int(max(self._cell.max(), 0))
    light = self.floor.lightings[c]
    if c >= self.floor.num_rooms:
      cell = self.floor.cells[c]
      x, y = self.T_floor_cam[t, :2, 3]
      along = 0 if cell.hi[0] - cell.lo[0] > cell.hi[1] - cell.lo[1] else 1
      lamp = np.array([*cell.centre, HEIGHT - 0.3])
      lamp[along] = np.clip(4.0 * np.round((x, y)[along] / 4.0), cell.lo[along], cell.hi[along])
      light = light._replace(lamp_pos=lamp.astype(np.float32))
    return light

  def candidates(self, t: int) -> np.ndarray:
    """`(P,) bool` the primitives frame t may see: planes, and those whose bounding sphere
    comes within `MAX_RANGE` of the camera."""
    eye = self.T_floor_cam[t, :3, 3].astype(np.float64)
    near = np.linalg.norm(self._centre - eye, axis=1) - self._radius <= MAX_RANGE
    return near | self._plane

  def frame(self, t: int) -> RGBDFrame:
    """Renders frame t (its pose in the world frame, as the sequence reports it)."""
    if not 0 <= t < len(self):
      raise IndexError(f"frame {t} out of range for a walk of {len(self)} frames")
    world = self.floor.world._replace(lighting=self.lighting_at(t))
    key = jax.random.fold_in(jax.random.PRNGKey(self.floor.seed), t)
    f = synthetic.render(world, self.T_floor_cam[t], self.camera, height=self.height,
                         width=self.width, realism=self.realism, key=key,
                         tile_sizes=TILE_SIZES, pack_step=256, sensing=self.sensing,
                         candidates=self.candidates(t))
    far = f.depth * self._ray_scale > MAX_RANGE
    return f._replace(depth=np.where(far, 0.0, f.depth).astype(np.float32),
                      labels=np.where(far, 0, f.labels), instances=np.where(far, 0, f.instances),
                      T_world_cam=self.T_world_cam[t])

  def __iter__(self) -> Iterator[RGBDFrame]:
    return (self.frame(t) for t in range(len(self)))

  def sequence(self, start: int = 0, stop: Optional[int] = None) -> RGBDSequence:
    """Frames `[start, stop)` rendered into an `RGBDSequence` (`info["frame_ids"]`)."""
    ids = list(range(len(self)))[start:stop]
    if not ids:
      raise ValueError(f"no frames in [{start}, {stop}) of a walk of {len(self)} frames")
    frames = [self.frame(t) for t in ids]
    return RGBDSequence(
        name=self.name, class_names=CLASS_NAMES, camera=self.camera,
        rgb=np.stack([f.rgb for f in frames]), depth=np.stack([f.depth for f in frames]),
        T_world_cam=self.T_world_cam[ids], labels=np.stack([f.labels for f in frames]),
        instances=np.stack([f.instances for f in frames]), info=self.info(ids))

  def info(self, frame_ids=None) -> dict:
    """The provenance `info` of the walk's sequences."""
    floor = self.floor
    return {"source": "floor", "num_rooms": floor.num_rooms, "seed": floor.seed,
            "domain": floor.world.domain, "shift": floor.world.shift,
            "realism": self.realism, "max_range_m": MAX_RANGE, "step_m": STEP,
            "walk_frames": self.walk_frames,
            "room_envs": [layout.env for layout in floor.room_layouts],
            "extent_m": [float(x) for x in floor.world.layout.room],
            "T_world_floor": floor.T_world_floor.tolist(),
            "frame_ids": list(range(len(self))) if frame_ids is None else list(frame_ids)}


def make_floor_sequence(num_rooms: int, *, seed: int = 0, domain: str = "test",
                        shift: float = 1.0, num_frames: Optional[int] = None, stride: int = 1,
                        height: int = 120, width: int = 160, realism: bool = True,
                        sensing=None) -> RGBDSequence:
  """The first `num_frames` frames (every `stride`-th; None: all) of a floor's walk, rendered.

  Args:
    num_rooms: N rooms (`make_floor`).
    seed: layout seed.
    domain: "train" or "test" appearance.
    shift: strength of the "test" domain gap in [0, 1].
    num_frames: the most frames (None: the whole walk, one frame every `STEP` · stride metres).
    stride: keep every stride-th frame of the walk.
    height: image rows H.
    width: image columns W.
    realism: sensor noise on depth and the camera model on colour (labels stay exact).
    sensing: the camera model (`SensingConfig`; default `SensingConfig()`).

  Returns:
    An `RGBDSequence` named `f"floor_{N}_{domain}"` with `CLASS_NAMES` labels; `(T, H, W)`
    frames. For walks too long to hold, iterate a `FloorWalk` instead.
  """
  walk = FloorWalk(make_floor(num_rooms, seed=seed, domain=domain, shift=shift),
                   num_frames=num_frames, stride=stride, height=height, width=width,
                   realism=realism, sensing=sensing)
  return walk.sequence()
