"""Shared builders for the engine tests: small random frames with the bad data docs/equations.md
(§2.1, §5) says the engine must survive (holes, NaN/inf depth, one-hot pixels, zero variance)."""

import numpy as np
import pytest

import jaxfusion as jf

PAPER_RULES = ("sum_probs", "sum_labels", "bayes", "robust_r", "robust_d", "robust_dr")
DIRICHLET_RULES = ("robust_d", "robust_dr")


def main_tier_keeps(values, keep):
  """`values` as pytest parameters, those not in `keep` in the slow tier: a property checked
  over many cases keeps a few in the main tier (its time budget) and every case in CI."""
  return [v if v in keep else pytest.param(v, marks=pytest.mark.slow) for v in values]


HEIGHT, WIDTH, NUM_CLASSES = 6, 8, 4
CAMERA = jf.Camera(6.0, 6.0, 3.5, 2.5)


def rotation(axis_angle):
  """Rodrigues' formula, float64."""
  theta = np.linalg.norm(axis_angle)
  if theta < 1e-12:
    return np.eye(3)
  k = axis_angle / theta
  Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
  return np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * Kx @ Kx


def pose(rng, spread=0.3):
  T = np.eye(4)
  T[:3, :3] = rotation(rng.normal(0, spread, 3))
  T[:3, 3] = rng.normal(0, spread, 3)
  return T.astype(np.float32)


def drop_ambiguous_pixels(depth, T, camera, voxel_size, margin=1e-3):
  """Makes a hole of every pixel whose point lies within `margin` voxels of a voxel face, where
  float32 (engine) and float64 (reference) rounding could disagree on its voxel."""
  depth = depth.copy()
  T64 = T.astype(np.float64)
  H, W = depth.shape
  v, u = np.mgrid[0:H, 0:W]
  d = depth.astype(np.float64)
  with np.errstate(invalid="ignore"):
    p_cam = np.stack([d * (u - camera.cx) / camera.fx, d * (v - camera.cy) / camera.fy, d], -1)
    scaled = (p_cam @ T64[:3, :3].T + T64[:3, 3]) / voxel_size
    frac = scaled - np.floor(scaled)
    near = np.any(np.minimum(frac, 1 - frac) < margin, axis=-1)
  depth[near & np.isfinite(depth)] = 0.0
  return depth


def random_frame(rng, *, height=HEIGHT, width=WIDTH, num_classes=NUM_CLASSES, voxel_size=0.25,
                 camera=CAMERA, T=None):
  """A Frame with holes (0, NaN, inf, negative depth), one-hot pixels, exact zeros in the
  probabilities and zero-variance pixels."""
  depth = rng.uniform(0.4, 1.6, (height, width)).astype(np.float32)
  holes = rng.random((height, width)) < 0.15
  depth[holes] = rng.choice(np.array([0.0, np.nan, np.inf, -1.0], np.float32), holes.sum())
  T = pose(rng) if T is None else T
  depth = drop_ambiguous_pixels(depth, T, camera, voxel_size)
  probs = rng.dirichlet(np.full(num_classes, 0.5), (height, width))
  one_hot = rng.random((height, width)) < 0.2
  probs[one_hot] = np.eye(num_classes)[rng.integers(0, num_classes, one_hot.sum())]
  var = rng.uniform(0.0, 0.05, (height, width, num_classes))
  var[rng.random((height, width)) < 0.2] = 0.0
  return jf.Frame(depth, T, probs.astype(np.float32), var.astype(np.float32))


def rule_kwargs(name, **hparams):
  return {k: v for k, v in hparams.items()
          if name.startswith("robust") or k == "aggregate"}
