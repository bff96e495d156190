"""Changing worlds: rooms whose objects move between two visits, and drifting odometry.

An embedded sequence can carry one of three changes (`CHANGES`; `make_changing_sequence`, the
spec tail `office:0:moved`):

* "moved" — two passes along the same trajectory: the first through the room of
  `(env, seed)`, the second through `changed_layout`'s room, in which two objects stand
  elsewhere, one is gone and one is new;
* "final" — the same two passes, both through the changed room: the reference world in which
  the objects always stood where they end;
* "drift" — one ordinary pass whose stored poses are drifted odometry (`drift_poses`), as a
  visual-odometry front end would give; depth, colour and labels are rendered from the true
  poses, which `info["true_poses"]` keeps.

A two-pass sequence of T frames has `t1 = T // 2` frames in pass 1 and the rest in pass 2
(`info["passes"] = [[0, t1], [t1, T]]`), each walking the whole trajectory. Its
`info["gt_frames"] = [t1, T]` names the frames that saw the final scene, the only frames
`ground_truth.gt_voxel_labels` fuses: "moved" and "final" are scored against the same GT.
Pass 2 of "moved" and of "final" are the same frames, bit for bit.

Shape legend: T frames, H×W pixels.
"""

import dataclasses
from typing import Optional

import jax
import numpy as np

from jaxfusion.datasets import scene, synthetic, trajectories
from jaxfusion.datasets.classes import BACKGROUND, CHAIR
from jaxfusion.datasets.sequence import RGBDSequence
# The renderer's own steps, shared with `synthetic.make_sequence` (same package).
from jaxfusion.datasets.synthetic import (  # pylint: disable=protected-access
    _check_sensing, _render_path, _sequence_info, _stack_frames)

CHANGES = ("moved", "final", "drift")
# Kinds an object may have to be moved or removed: light things that stand on the floor
# (floor lamps are left alone: they are taller than the camera path's clearance).
MOVABLE_KINDS = ("chair", "stool", "trash_bin", "box", "plant")
NUM_MOVED = 2
# A moved object's footprint centre lands at least this far (m) from where it stood.
MIN_MOVE = 1.0
# A footprint closer than this (m) to a wall stands against it; free-standing objects are
# picked first.
WALL_CLEARANCE = 0.25
# New spots keep their footprint this far (m) from every wall, in view of the trajectories.
INTERIOR_MARGIN = 0.6
# Clearance (m) between the footprint circle of a moved or added object and any other.
FOOTPRINT_GAP = 0.05
SPOT_TRIES = 400
# Odometry drift per frame: RMS norm of the translation error (m) and of the rotation error
# (degrees) of each relative motion.
DRIFT_TRANSLATION = 0.01
DRIFT_ROTATION_DEG = 0.15


def _radius(pl: scene.Placement) -> float:
  """Radius of the footprint circle of a placement (as `scene._Planner` draws them)."""
  return float(0.5 * np.hypot(pl.size[0], pl.size[1]))


def _on_floor(pl: scene.Placement) -> bool:
  """Whether a placement has a floor footprint (stands at z = 0, and is not a rug)."""
  return float(pl.position[2]) == 0.0 and pl.kind != "rug"


def footprints(layout: scene.Layout) -> dict:
  """The floor footprints of a layout: instance id → `(x, y, r)` circle in the room frame."""
  return {pl.instance: (float(pl.position[0]), float(pl.position[1]), _radius(pl))
          for pl in layout.placements if _on_floor(pl)}


def _carries(base: scene.Placement, placements) -> bool:
  """Whether anything stands on top of `base`."""
  top = float(base.position[2] + base.size[2])
  r = _radius(base)
  return any(float(p.position[2]) > 0.0 and abs(float(p.position[2]) - top) < 1e-6 and
             np.hypot(*(p.position[:2] - base.position[:2])) <= r for p in placements)


def _wall_clearance(room, x: float, y: float, r: float) -> float:
  return float(min(x - r, y - r, room[0] - x - r, room[1] - y - r))


def _free(circles: dict, x: float, y: float, r: float, ignore: int) -> bool:
  return all(np.hypot(x - cx, y - cy) >= r + cr + FOOTPRINT_GAP
             for owner, (cx, cy, cr) in circles.items() if owner != ignore)


def _free_spot(rng: np.random.Generator, room, circles: dict, r: float, *, ignore: int = -1,
               away_from=None) -> Optional[tuple]:
  """A free floor spot `(x, y)` for a footprint of radius `r`, or None after `SPOT_TRIES`."""
  lo, hi = INTERIOR_MARGIN + r, np.asarray(room[:2], np.float64) - INTERIOR_MARGIN - r
  if np.any(hi <= lo):
    return None
  for _ in range(SPOT_TRIES):
    x, y = rng.uniform(lo, hi)
    if away_from is not None and np.hypot(x - away_from[0], y - away_from[1]) < MIN_MOVE:
      continue
    if _free(circles, x, y, r, ignore):
      return float(x), float(y)
  return None


def _movable(layout: scene.Layout, rng: np.random.Generator) -> list:
  """The objects that may move or vanish, free-standing ones first (each group shuffled)."""
  ok = [pl for pl in layout.placements
        if pl.kind in MOVABLE_KINDS and _on_floor(pl) and not _carries(pl, layout.placements)]
  free = [pl for pl in ok if _wall_clearance(layout.room, pl.position[0], pl.position[1],
                                             _radius(pl)) >= WALL_CLEARANCE]
  walled = [pl for pl in ok if pl not in free]
  return ([free[i] for i in rng.permutation(len(free))] +
          [walled[i] for i in rng.permutation(len(walled))])


def _xyz(position) -> list:
  return [round(float(v), 6) for v in position]


def changed_layout(layout: scene.Layout, seed: Optional[int] = None) -> tuple:
  """The same room at a second visit, in which some objects changed.

  Drawn from `(layout.env, seed)` alone: of the movable objects (`MOVABLE_KINDS` standing on
  the floor with nothing on top; free-standing ones before those against a wall, each group in
  a random order) the first is removed and the next `NUM_MOVED` that find a spot are moved: to
  a random floor spot whose footprint circle keeps `INTERIOR_MARGIN` from the walls,
  `FOOTPRINT_GAP` from every other footprint (of the changed room) and lies at least
  `MIN_MOVE` from where it stood, turned by a yaw uniform in ±90°. One new object (a chair or
  a box, even odds) is added at such a spot, with the next free instance id. Everything else
  is kept as it was.

  Args:
    layout: a `scene.Layout` (`scene.make_layout`).
    seed: seed of the change (default `layout.seed`).

  Returns:
    `(Layout, record)`: the changed layout (same room, seed and lighting) and the JSON-
    serialisable change record with `moved`, `removed`, `added` (lists of instance ids),
    `kinds` (id → kind), `old_positions` / `old_yaws` (of the moved and removed objects) and
    `new_positions` / `new_yaws` (of the moved and added ones), keyed by the id as a string;
    positions are `[x, y, z]` in the room's frame (a sequence's world frame puts the room at
    `info["T_world_room"]`).

  Raises:
    ValueError: fewer than `NUM_MOVED + 1` movable objects, or no free spot for them.
  """
  if not isinstance(layout, scene.Layout):
    raise ValueError(f"layout must be a scene.Layout; got a {type(layout).__name__}")
  seed = layout.seed if seed is None else seed
  if int(seed) < 0:
    raise ValueError(f"seed must be a non-negative integer; got {seed}")
  rng = np.random.default_rng([int(seed), scene.ENVIRONMENTS.index(layout.env), 8117])
  pool = _movable(layout, rng)
  if len(pool) < NUM_MOVED + 1:
    raise ValueError(f"{layout.env} seed {layout.seed}: {len(pool)} movable objects, "
                     f"{NUM_MOVED + 1} needed")
  circles = footprints(layout)
  removed = pool[0]
  del circles[removed.instance]
  moved = {}
  for pl in pool[1:]:
    if len(moved) == NUM_MOVED:
      break
    r = _radius(pl)
    spot = _free_spot(rng, layout.room, circles, r, ignore=pl.instance, away_from=pl.position)
    if spot is None:
      continue
    circles[pl.instance] = (*spot, r)
    moved[pl.instance] = pl._replace(position=np.array([spot[0], spot[1], 0.0]),
                                     yaw=float(pl.yaw + rng.uniform(-np.pi / 2, np.pi / 2)))
  if len(moved) < NUM_MOVED:
    raise ValueError(f"{layout.env} seed {layout.seed}: no free floor spot for "
                     f"{NUM_MOVED - len(moved)} of the objects to move")
  if rng.uniform() < 0.5:
    kind, label, e = "chair", CHAIR, rng.uniform(0.46, 0.5)
    size = np.array([e, e, 0.0])
  else:
    kind, label, e = "box", BACKGROUND, rng.uniform(0.3, 0.55)
    size = np.array([e, e * rng.uniform(0.7, 1.0), e * rng.uniform(0.6, 1.0)])
  instance = max(pl.instance for pl in layout.placements) + 1
  r = float(0.5 * np.hypot(size[0], size[1]))
  spot = _free_spot(rng, layout.room, circles, r)
  if spot is None:
    raise ValueError(f"{layout.env} seed {layout.seed}: no free floor spot for a new {kind}")
  added = scene.Placement(kind, label, instance, np.array([spot[0], spot[1], 0.0]),
                          float(rng.uniform(-np.pi, np.pi)), size,
                          rng.uniform(size=len(removed.u)))
  placements = tuple(moved.get(pl.instance, pl) for pl in layout.placements
                     if pl.instance != removed.instance) + (added,)
  old = [layout.placements[[p.instance for p in layout.placements].index(i)]
         for i in list(moved) + [removed.instance]]
  new = list(moved.values()) + [added]
  record = {
      "moved": [int(i) for i in moved], "removed": [int(removed.instance)],
      "added": [int(instance)],
      "kinds": {str(p.instance): p.kind for p in new + [removed]},
      "old_positions": {str(p.instance): _xyz(p.position) for p in old},
      "old_yaws": {str(p.instance): round(float(p.yaw), 6) for p in old},
      "new_positions": {str(p.instance): _xyz(p.position) for p in new},
      "new_yaws": {str(p.instance): round(float(p.yaw), 6) for p in new},
  }
  return layout._replace(placements=placements), record


def _rotation(omega: np.ndarray) -> np.ndarray:
  """`(3, 3)` rotation of the axis-angle vector `omega (3,)` (Rodrigues)."""
  theta = float(np.linalg.norm(omega))
  if theta < 1e-15:
    return np.eye(3)
  k = omega / theta
  K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
  return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * K @ K


def drift_poses(T_world_cam, *, seed, translation: float = DRIFT_TRANSLATION,
                rotation_deg: float = DRIFT_ROTATION_DEG) -> np.ndarray:
  """Odometry poses that drift from the true ones as a random walk.

  Each relative motion `inv(T[t-1]) @ T[t]` is chained with a small error `E_t` in the camera
  frame: `D[0] = T[0]`, `D[t] = D[t-1] @ inv(T[t-1]) @ T[t] @ E_t`, where `E_t` turns by an
  axis-angle vector and shifts by a vector, each `(b + n_t) / √2` with a bias `b` drawn once
  and a fresh `n_t` per frame, both normal with independent axes and RMS norm `rotation_deg`
  (degrees) or `translation` (m); the per-frame error keeps that RMS size. The error starts at
  0 and grows along the sequence, about linearly (the bias: odometry drifts one way) with a
  random walk on top; rotation errors swing the later motions.

  Args:
    T_world_cam: `(T, 4, 4)` true camera-to-world poses.
    seed: seed of the errors (an int or a sequence of ints, as `np.random.default_rng` takes).
    translation: RMS translation error per frame in metres (≥ 0).
    rotation_deg: RMS rotation error per frame in degrees (≥ 0).

  Returns:
    `(T, 4, 4) float64` drifted camera-to-world poses.

  Raises:
    ValueError: poses of the wrong shape, or a negative error size.
  """
  T = np.asarray(T_world_cam, np.float64)
  if T.ndim != 3 or T.shape[1:] != (4, 4):
    raise ValueError(f"T_world_cam must be (T, 4, 4); got {T.shape}")
  if not (translation >= 0 and rotation_deg >= 0):
    raise ValueError(f"drift sizes must be ≥ 0; got translation {translation}, rotation "
                     f"{rotation_deg}°")
  rng = np.random.default_rng(seed)
  sigma_t = translation / np.sqrt(3.0)
  sigma_r = np.radians(rotation_deg) / np.sqrt(3.0)
  bias_r, bias_t = rng.normal(0.0, sigma_r, 3), rng.normal(0.0, sigma_t, 3)
  out = np.empty_like(T)
  if len(T):
    out[0] = T[0]
  for t in range(1, len(T)):
    error = np.eye(4)
    error[:3, :3] = _rotation((bias_r + rng.normal(0.0, sigma_r, 3)) / np.sqrt(2.0))
    error[:3, 3] = (bias_t + rng.normal(0.0, sigma_t, 3)) / np.sqrt(2.0)
    out[t] = out[t - 1] @ np.linalg.inv(T[t - 1]) @ T[t] @ error
  return out


def _merge_states(records: list) -> dict:
  """The camera states of consecutive passes as one record (per-frame lists joined)."""
  out = {"frame_interval_s": records[0]["frame_interval_s"],
         "frame_interval_s_per_pass": [r["frame_interval_s"] for r in records]}
  for name, value in records[0].items():
    if isinstance(value, list):
      out[name] = [x for r in records for x in r[name]]
  return out


def make_changing_sequence(env: str, trajectory: int, *, change: str, domain: str = "test",
                           num_frames: int = 60, height: int = 120, width: int = 160,
                           seed: int = 0, shift: float = 1.0, realism: bool = True,
                           sensing=None) -> RGBDSequence:
  """An embedded sequence through a changing world (see the module docstring).

  For "moved" and "final", pass `p` (0 or 1) renders the trajectory with
  `num_frames // 2` (pass 1) or the remaining (pass 2) frames; the frames' PRNG keys are those
  of the `num_frames`-frame static sequence, and with `realism` the camera model restarts at
  pass 2 (its own draws; `info["camera_states"]` joins the two passes' per-frame lists and
  keeps each pass's frame interval in `frame_interval_s_per_pass`). For "drift" the sequence
  is `synthetic.make_sequence`'s with the poses replaced by `drift_poses` (seeded by
  `(seed, trajectory, env)`).

  Args:
    env: "office" or "house".
    trajectory: 0, 1 or 2.
    change: one of `CHANGES`.
    domain: "train" or "test" appearance.
    num_frames: T frames in all (≥ 2 for the two-pass kinds).
    height: image rows H.
    width: image columns W.
    seed: layout seed (also the seed of the change and of the drift).
    shift: strength of the "test" domain gap in [0, 1].
    realism: sensor noise and the camera model, as in `synthetic.make_sequence`.
    sensing: the camera model (default `SensingConfig()`).

  Returns:
    An `RGBDSequence` named `f"{env}_{trajectory}_{domain}_{change}"`, with the static
    sequence's `info` and `info["change"]`; for "moved" / "final" also `info["passes"]`
    (`[[0, t1], [t1, T]]`), `info["gt_frames"]` (`[t1, T]`) and `info["changes"]` (the
    record of `changed_layout`); for "drift" `info["true_poses"]` (`T` lists of 4 × 4, the
    true world-frame `T_world_cam`) and `info["drift"]` (the error sizes per frame).

  Raises:
    ValueError: an unknown change, too few frames, or the arguments `make_sequence` refuses.
  """
  if change not in CHANGES:
    raise ValueError(f"change must be one of {'|'.join(CHANGES)}; got {change!r}")
  name = f"{env}_{trajectory}_{domain}_{change}"
  if change == "drift":
    seq = synthetic.make_sequence(env, trajectory, domain=domain, num_frames=num_frames,
                                  height=height, width=width, seed=seed, shift=shift,
                                  realism=realism, sensing=sensing)
    drifted = drift_poses(seq.T_world_cam, seed=[int(seed), int(trajectory),
                                                 scene.ENVIRONMENTS.index(env), 9413])
    info = dict(seq.info, change=change, true_poses=seq.T_world_cam.tolist(),
                drift={"translation_m_per_frame": DRIFT_TRANSLATION,
                       "rotation_deg_per_frame": DRIFT_ROTATION_DEG})
    return dataclasses.replace(seq, name=name, T_world_cam=drifted.astype(np.float32),
                               info=info)
  if env not in scene.ENVIRONMENTS:
    raise ValueError(f"env must be one of {scene.ENVIRONMENTS}; got {env!r}")
  if trajectory not in range(synthetic.NUM_TRAJECTORIES):
    raise ValueError(f"trajectory must be 0, 1 or 2; got {trajectory}")
  if height < 1 or width < 1:
    raise ValueError(f"image size must be positive; got {height}x{width}")
  if num_frames < 2:
    raise ValueError(f"a {change!r} sequence has two passes: num_frames must be ≥ 2; got "
                     f"{num_frames}")
  config = _check_sensing(sensing)
  original = scene.make_layout(env, seed)
  changed, record = changed_layout(original)
  layouts = (original, changed) if change == "moved" else (changed, changed)
  t1 = num_frames // 2
  passes = [[0, t1], [t1, num_frames]]
  camera = synthetic.default_camera(height, width)
  keys = jax.random.split(jax.random.PRNGKey(seed * 7 + trajectory), num_frames)
  frames, poses, states, info = [], [], [], None
  for p, ((start, stop), layout) in enumerate(zip(passes, layouts)):
    world = synthetic.scene_from_layout(layout, domain=domain, shift=shift)
    path = trajectories.trajectory(layout.room, trajectory, stop - start)
    rng = np.random.default_rng([seed, trajectory, scene.ENVIRONMENTS.index(env), 5151, p])
    got, state = _render_path(
        world, path, keys[start:stop], camera, config, realism=realism, height=height,
        width=width, rng=rng)
    frames += got
    poses.append(path)
    states.append(state)
    if info is None:
      info = _sequence_info(world, trajectory, seed=seed, realism=realism)
  if states[0] is not None:
    info["camera_states"], info["sensing"] = _merge_states(states), config.as_dict()
  info.update(change=change, passes=passes, gt_frames=[t1, num_frames], changes=record)
  T_world_cam = np.einsum("ij,tjk->tik", synthetic.placement(env, seed), np.concatenate(poses))
  return _stack_frames(name, camera, frames, T_world_cam, info)
