"""Figures are written as PNGs; the outlier example is computed by the engine."""

import numpy as np

from jaxfusion.lab import figures


def test_outlier_example_flips_bayes_only(tmp_path):
  path = str(tmp_path / "outlier.png")
  ex = figures.outlier_figure(path)
  assert np.argmax(ex["prior"]["Bayesian"]) == 0
  assert np.argmax(ex["posterior"]["Bayesian"]) == 1
  for name in ("R", "D", "D+R"):
    assert np.argmax(ex["posterior"][name]) == 0, name
  with open(path, "rb") as f:
    assert f.read(8) == b"\x89PNG\r\n\x1a\n"


def test_iou_bars_and_map_views(tmp_path):
  figures.iou_bars(str(tmp_path / "iou.png"), {"Bayes": np.array([0.5, np.nan, 0.2]),
                                               "D+R": np.array([0.6, 0.1, 0.3])},
                   ["a", "b", "c"], colors=np.array([[0, 0, 0], [255, 0, 0], [255, 255, 255]]))
  rng = np.random.default_rng(0)
  voxels = {"coords": rng.integers(0, 20, (200, 3)), "labels": rng.integers(0, 3, 200)}
  figures.map_views(str(tmp_path / "maps.png"), {"GT": voxels, "D+R": voxels}, voxel_size=0.1,
                    colors=np.array([[0, 0, 0], [255, 0, 0], [0, 0, 255]], np.uint8))
  for name in ("iou.png", "maps.png"):
    assert (tmp_path / name).stat().st_size > 1000
