"""The changing-world bench (bench.changing) runs at its `--quick` sizes and writes what it reports.
No timings are asserted: `python -m bench.changing` measures them."""

import json

import numpy as np
import pytest

from bench import changing
from bench import scene
from jaxfusion import deintegration


def test_pose_correction_is_rigid_small_and_grows_along_the_stack():
  poses = scene.make_frames(3, height=12, width=16, num_classes=7).poses
  new = changing.corrected_poses(poses, 0.5, 0.02)
  deintegration.check_poses(new, 3, "new_poses")
  moved = np.linalg.norm(new[:, :3, 3] - poses[:, :3, 3], axis=1)
  assert np.all((0 < moved) & (moved < 0.1))
  rel = np.einsum("tji,tjk->tik", poses[:, :3, :3].astype(np.float64), new[:, :3, :3])
  angle = np.degrees(np.arccos(np.clip((np.trace(rel, axis1=1, axis2=2) - 1) / 2, -1, 1)))
  assert np.all(np.diff(angle) > 0) and angle[-1] == pytest.approx(0.5, abs=0.01)


@pytest.mark.slow   # eleven programs compiled (five maps, three de-integration calls): ~20–40 s
def test_quick_run_writes_every_measurement(tmp_path, capsys):
  result = changing.main(["--quick", "--out", str(tmp_path)])
  data = json.loads((tmp_path / "changing.json").read_text())
  assert data["command"] == "python -m bench.changing --quick"
  assert data == json.loads(json.dumps(result))
  assert len(data["load_avg_at_start"]) == 3
  for stats in data["maps"].values():
    assert stats["capacity"] == 2**14 and 0 < stats["load"] < 0.5 and stats["dropped"] == 0
  assert data["maps"]["dr_on"]["free"] >= 0 and "free" not in data["maps"]["dr_off"]
  assert data["maps"]["bayes_geometry"]["geometry"]["blocks"] > 0
  for rule in ("dr", "bayes"):
    f = data["free_space"][rule]
    assert f["pass_ms"] == pytest.approx(f["on"]["ms_per_frame"] - f["off"]["ms_per_frame"])
  for key in ("reintegrate", "reintegrate_geometry"):
    x = data[key]
    assert all(x[op]["ms_per_frame"] > 0 for op in ("fuse_sequence", "reintegrate",
                                                    "unfuse_frame", "fuse_frame"))
    assert x["reintegrate_over_fuse_sequence"] == pytest.approx(
        x["reintegrate"]["ms_per_frame"] / x["fuse_sequence"]["ms_per_frame"])
    assert x["unfuse_frame"]["calls"] == data["config"]["repeats"] * x["stack"]
  text = capsys.readouterr().out
  assert "free-space pass (on − off)" in text and "Bayes + TSDF `reintegrate`" in text
