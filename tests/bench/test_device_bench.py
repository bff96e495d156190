"""The device bench (bench.device) runs on its quick configuration and writes every measurement.
No timings are asserted beyond being positive and finite: `python -m bench.device` measures them."""

import json
import math

import pytest

from bench import device


def _times(results: dict) -> list:
  """Every `(name, value)` of a time or rate in the results."""
  found = []
  for name, row in results["fuse_frame"].items():
    found += [(f"fuse_frame.{name}.{k}", row[k]) for k in ("ms_per_frame", "frames_per_s")]
  for row in results["tsdf"]:
    found += [(f"tsdf.{row['voxel_size']}.{k}", row[k])
              for k in ("integrate_ms_per_frame", "integrate_frames_per_s", "mesh_ms")]
  for name, row in results["mc"].items():
    if "skipped" not in row:
      found += [(f"mc.{name}.{k}", row[k]) for k in ("ms_per_frame", "frames_per_s")]
  found += [(f"fuse_batch.{k}", results["fuse_batch"][k]) for k in ("ms_per_call", "frames_per_s")]
  found += [(f"mapper.{k}", results["mapper"][k]) for k in (
      "mapper_plain", "fuse_frame_plain", "mapper_waiting", "fuse_frame_waiting")]
  return found


@pytest.mark.slow   # 16 programs compiled (six rules, TSDF, mesh, net, moments, batch, Mapper)
def test_quick_run_writes_every_measurement(tmp_path, capsys):
  device.main(["--quick", "--out", str(tmp_path)])
  results = json.loads((tmp_path / "device.json").read_text())
  assert {"backend", "machine", "config", "nvblox", "fuse_frame", "tsdf", "mc",
          "fuse_batch", "mapper"} <= set(results)
  assert results["backend"]["default_backend"] and results["backend"]["devices"]
  assert set(results["fuse_frame"]) == set(device.jf.rules.PAPER_RULES)
  assert [r["voxel_size"] for r in results["tsdf"]] == [0.1]
  assert {"network_samples", "mc_moments"} <= set(results["mc"])
  assert "skipped" not in results["mc"]["mc_moments"]
  for name, value in _times(results):
    assert isinstance(value, float) and math.isfinite(value) and value > 0, (name, value)
  table = capsys.readouterr().out
  assert "nvblox, RTX 3090, published" in table and "| fuse_frame D+R" in table
  assert "| Mapper (both layers) beside fuse_frame, 160×120, a plain loop" in table
  assert results["mapper"]["turns"] == 2 and results["mapper"]["frames_per_turn"] == 4
