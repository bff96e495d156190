"""`jaxfusion changing-world` (jaxfusion/lab/changing.py): the ghost region and shares by hand, and
the whole command on a tiny world with the simulated front end (slow tier)."""

import json
import os

import numpy as np
import pytest

from jaxfusion.lab import changing
from jaxfusion.lab import sequences


def test_ghost_shares_by_hand():
  region = {"coords": np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]),
            "labels": np.array([2, 2, 3, 3]), "reachable": np.array([True, True, True, False])}
  voxels = {"coords": np.array([[1, 0, 0], [2, 0, 0], [3, 0, 0], [9, 9, 9]], np.int32),
            "labels": np.array([2, 1, 3, 2])}
  shares = changing.ghost_shares(voxels, region)
  assert shares["read_out"] == pytest.approx(75.0)          # 3 of 4 still there
  assert shares["ghost"] == pytest.approx(50.0)             # [1] and [3] keep their class
  assert shares["ghost_reachable"] == pytest.approx(100 / 3)   # of [0], [1], [2]: only [1]
  empty = changing.ghost_shares(voxels, {k: v[:0] for k, v in region.items()})
  assert np.isnan(empty["ghost"])


def test_settings_compare_off_octomap_and_the_calibrated_clamp():
  assert list(changing.settings(0.971)) == ["off", "on"]
  three = changing.settings(0.8)
  assert list(three) == ["off", "on", "calibrated"] and three["calibrated"].clamp_max == 0.8


@pytest.mark.slow
def test_the_ghost_region_is_free_in_the_final_scene():
  options = sequences.DataOptions(num_frames=8, height=32, width=48, num_samples=2)
  moved = sequences.load("office:0:s1:moved", options, front_end=sequences.SIMULATED)
  region = changing.ghost_region(moved, 0.1)
  assert len(region["coords"]) > 0
  final = {tuple(c) for c in np.asarray(moved.gt["coords"])}
  assert not final & {tuple(c) for c in region["coords"]}
  assert all(0 <= label < len(moved.class_names) for label in region["labels"])
  assert region["reachable"].dtype == bool


@pytest.mark.slow
def test_the_command_writes_its_page_figure_and_numbers(tmp_path):
  config = changing.ChangingConfig(layout_seeds=(1,), num_frames=8, height=32, width=48,
                                   num_samples=2, rules=("bayes",), calibration_seeds=(11,),
                                   clamp_grid=(0.971, 0.7))
  page = str(tmp_path / "page.md")
  result = changing.run(config, str(tmp_path / "out"), front_end=sequences.SIMULATED,
                        page=page, figure=None)
  assert os.path.exists(page) and "Ghost region" in open(page).read()
  saved = json.load(open(tmp_path / "out" / "changing.json"))
  assert saved["calibration"]["clamp_max"] in (0.971, 0.7)
  rows = result["summary"]["rows"]
  assert rows["bayes/off"]["read_out"] >= 95.0     # keys rounded in float64 here
  assert rows["bayes/on"]["read_out"] <= rows["bayes/off"]["read_out"]
  drift = result["summary"]["drift"]["bayes"]
  assert drift["corrected"]["miou"] == pytest.approx(drift["scratch"]["miou"], abs=0.5)
  assert drift["corrected"]["chamfer_cm"] == pytest.approx(drift["scratch"]["chamfer_cm"],
                                                           abs=0.1)
