"""Smooth camera paths through a room (camera-to-world poses, OpenCV camera frame).

Three trajectories per room, like the paper's three AirSim trajectories per environment:

* 0 — `"walk"`: a loop along the walls at eye height, looking into the room;
* 1 — `"orbit"`: a circle around the room centre, looking at the centre;
* 2 — `"sweep"`: an S-shaped walk-through across the room while the view pans left and right.

All paths are smooth (sums of sines over the normalised time) and stay ≥ 0.9 m from the
walls and ≥ 1.45 m above the floor, above the furniture that stands away from the walls.

Shape legend: T frames.
"""

import numpy as np

TRAJECTORY_NAMES = ("walk", "orbit", "sweep")


def look_at(eye, target) -> np.ndarray:
  """Camera-to-world pose of a camera at `eye` looking at `target` with the world z up.

  Args:
    eye: `(3,)` camera centre.
    target: `(3,)` point on the optical axis.

  Returns:
    `(4, 4) float32` `T_world_cam` (camera x right, y down, z forward).
  """
  eye = np.asarray(eye, np.float64)
  forward = np.asarray(target, np.float64) - eye
  forward /= np.linalg.norm(forward)
  right = np.cross(forward, [0.0, 0.0, 1.0])
  if np.linalg.norm(right) < 1e-6:  # looking straight up or down
    right = np.array([1.0, 0.0, 0.0])
  right /= np.linalg.norm(right)
  down = np.cross(forward, right)
  T = np.eye(4)
  T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, forward, eye
  return T.astype(np.float32)


def trajectory(room, index: int, num_frames: int) -> np.ndarray:
  """One of the three trajectories of a room.

  Args:
    room: `(3,)` room size `(Lx, Ly, H)`.
    index: 0 (walk), 1 (orbit) or 2 (sweep).
    num_frames: T ≥ 1.

  Returns:
    `(T, 4, 4) float32` camera-to-world poses.
  """
  if index not in (0, 1, 2):
    raise ValueError(f"trajectory index must be 0, 1 or 2; got {index}")
  if num_frames < 1:
    raise ValueError(f"num_frames must be ≥ 1; got {num_frames}")
  lx, ly, h = (float(x) for x in room)
  centre = np.array([lx / 2, ly / 2])
  s = np.arange(num_frames) / num_frames  # normalised time in [0, 1)
  eye_z = np.minimum(1.45 + 0.12 * (1 + np.sin(2 * np.pi * 2 * s)) / 2, h - 0.6)
  if index == 0:
    a = 2 * np.pi * s
    # A rounded rectangle (superellipse) 1.1 m inside the walls.
    ax, ay = lx / 2 - 1.1, ly / 2 - 1.1
    cx, sx = np.cos(a), np.sin(a)
    px = centre[0] + ax * np.sign(cx) * np.abs(cx) ** 0.5
    py = centre[1] + ay * np.sign(sx) * np.abs(sx) ** 0.5
    eye = np.stack([px, py, eye_z * np.ones_like(px)], -1)
    ahead = np.stack([-np.sin(a), np.cos(a)], -1)
    inward = centre - eye[:, :2]
    inward /= np.linalg.norm(inward, axis=-1, keepdims=True)
    gaze = 0.35 * ahead + 0.65 * inward
    target = np.concatenate([eye[:, :2] + 2.5 * gaze, 0.55 * np.ones((num_frames, 1))], -1)
  elif index == 1:
    a = 2 * np.pi * s + 0.3
    r = min(lx, ly) / 2 - 1.0
    eye = np.stack([centre[0] + r * np.cos(a), centre[1] + r * np.sin(a),
                    np.full_like(a, min(1.75, h - 0.5))], -1)
    wobble = 0.4 * np.stack([np.sin(2 * np.pi * 3 * s), np.cos(2 * np.pi * 2 * s)], -1)
    target = np.concatenate([centre + wobble, 0.45 * np.ones((num_frames, 1))], -1)
  else:
    ax, ay = lx / 2 - 1.0, ly / 2 - 1.0
    a = 2 * np.pi * s
    px = centre[0] + ax * np.sin(a)
    py = centre[1] + ay * np.sin(2 * a) * 0.9
    eye = np.stack([px, py, eye_z * np.ones_like(px)], -1)
    vel = np.stack([ax * np.cos(a), 2 * 0.9 * ay * np.cos(2 * a)], -1)
    ahead = vel / np.linalg.norm(vel, axis=-1, keepdims=True)
    inward = centre - eye[:, :2]
    inward /= np.maximum(np.linalg.norm(inward, axis=-1, keepdims=True), 0.3)
    gaze = 0.5 * ahead + inward
    heading = np.arctan2(gaze[:, 1], gaze[:, 0]) + 0.6 * np.sin(2 * np.pi * 4 * s)
    target = np.stack([px + 2.0 * np.cos(heading), py + 2.0 * np.sin(heading),
                       0.5 * np.ones_like(px)], -1)
  return np.stack([look_at(e, t) for e, t in zip(eye, target)])


def random_view(rng: np.random.Generator, room, *, target=None) -> np.ndarray:
  """A random view from inside a room, for training images.

  Args:
    rng: NumPy generator.
    room: `(3,)` room size.
    target: optional `(3,)` point to look at (jittered); else a random point in the room.

  Returns:
    `(4, 4) float32` `T_world_cam`.
  """
  lx, ly, h = (float(x) for x in room)
  eye = np.array([rng.uniform(0.8, lx - 0.8), rng.uniform(0.8, ly - 0.8),
                  rng.uniform(1.2, min(1.9, h - 0.4))])
  if target is None:
    target = np.array([rng.uniform(0.5, lx - 0.5), rng.uniform(0.5, ly - 0.5),
                       rng.uniform(0.2, 1.0)])
  target = np.asarray(target, np.float64) + rng.normal(0.0, 0.25, 3)
  if np.linalg.norm(target[:2] - eye[:2]) < 0.6:  # too steep: step back along the same line
    away = eye[:2] - target[:2] + 1e-3
    eye[:2] = np.clip(target[:2] + 0.9 * away / np.linalg.norm(away), 0.4, [lx - 0.4, ly - 0.4])
  return look_at(eye, target)
