"""`jaxfusion mesh-study` on a tiny run: files, rows, the learned rule's D+R special case equal
to D+R, Bayes against itself exactly zero, and the pooled mesh IoU equal to the per-sequence
confusions' sum."""

import json

import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import surface_metrics
from jaxfusion.lab import cli
from jaxfusion.lab import mesh_study
from tests.lab.test_study import CAPACITY, H, W, SimulatedFrontEnd


@pytest.mark.slow
def test_tiny_mesh_study_end_to_end(tmp_path):
  # The scene of test_demo.py and test_study.py (shared compiled shapes), 3 frames, 2 shifts.
  config = mesh_study.MeshStudyConfig.of(
      layout_seeds=(0,), shifts=(0.0, 1.0), envs=("office",), trajectories=(0,), num_frames=3,
      height=H, width=W, num_samples=3, capacity=CAPACITY, num_resamples=50,
      rules=("bayes", "robust_dr"), learned=jf.rules.learned_special_case("robust_dr"),
      learned_source="D+R special case",
      fitted=(("dr", "family", {"mix": 1.0, "beta": 0.3}),))   # the family's D+R member
  out = mesh_study.run_mesh_study(config, str(tmp_path), front_end=SimulatedFrontEnd())
  for name in ("mesh_study.md", "mesh_study.json", "mesh_study.png",
               "mesh_office_0_test_shift0.png"):
    assert (tmp_path / name).stat().st_size > 200, name
  payload = json.loads((tmp_path / "mesh_study.json").read_text())
  rows = payload["summary"]["rules"]
  assert list(rows) == ["bayes", "robust_dr", "learned", "fitted:dr"]
  assert rows["fitted:dr"]["display"] == "Family (dr)"
  assert abs(rows["fitted:dr"]["mesh_miou"] - rows["robust_dr"]["mesh_miou"]) < 0.01
  assert payload["config"]["fitted"] == [["dr", "family"]]
  assert rows["bayes"]["mesh_vs_bayes"] == [0.0, 0.0, 0.0]
  for key in ("voxel_miou", "mesh_miou", "mesh_accuracy", "mesh_iou"):
    np.testing.assert_array_equal(np.asarray(rows["learned"][key], float),
                                  np.asarray(rows["robust_dr"][key], float), err_msg=key)
  g = payload["summary"]["geometry"]
  assert 0 < g["chamfer_l1"] < 0.2 and 0 < g["fscore@0.05"] <= 1 and g["faces"] > 0
  assert len(payload["sequences"]) == 2
  by_shift = payload["summary"]["by_shift"]                # one sequence per shift here
  assert set(by_shift) == {"0", "1"} and "| shift |" in out["table"]
  assert by_shift["1"]["rules"]["robust_dr"]["mesh_vs_bayes"][1] == pytest.approx(
      by_shift["1"]["rules"]["robust_dr"]["mesh_vs_bayes"][2])
  assert "| D+R |" in out["table"] and "| Learned |" in out["table"]
  assert all(0 <= r["mesh_miou"] <= 1 for r in rows.values())


def test_pooled_mesh_iou_is_the_sum_of_the_sequences_area_confusions():
  k = 3
  rng = np.random.default_rng(0)
  sequences = []
  for _ in range(3):
    sequences.append({
        "voxel_confusion": {"bayes": rng.integers(0, 9, (k, k))},
        "mesh_confusion": {"bayes": surface_metrics.padded_confusion(rng.random((k, k)),
                                                                      rng.random(k))},
        "geometry": {key: 1.0 for key in mesh_study.GEOMETRY_KEYS + ("vertices", "faces",
                                                                     "area_m2")}})
  config = mesh_study.MeshStudyConfig.of(rules=("bayes",), num_resamples=20)
  row = mesh_study.summarize(sequences, config)["rules"]["bayes"]
  pooled = sum(s["mesh_confusion"]["bayes"] for s in sequences)
  tp = np.diag(pooled)[:k]
  iou = tp / (pooled[:k].sum(1) + pooled[:, :k].sum(0) - tp)
  assert row["mesh_miou"] == pytest.approx(iou.mean())
  assert row["mesh_accuracy"] == pytest.approx(tp.sum() / pooled[:k].sum())


def test_command_line_errors_are_one_line(capsys):
  assert cli.main(["mesh-study", "--quick", "--frames", "0", "--no-learned-rule"]) == 2
  assert "--frames must be at least 1" in capsys.readouterr().err
  assert cli.main(["mesh-study", "--quick", "--variant", "no-equals-sign"]) == 2
  assert "--variant takes TAG=PARAMS_JSON" in capsys.readouterr().err
