"""The building bench (bench.building) runs its quick path on a tiny floor. No timings are
asserted: `python -m bench.building` measures them."""

import json

import pytest

from bench import building


@pytest.mark.slow   # fuse, growth, read-out, query and meshing compiled at a few sizes, and
# two processes of table sizes: ~60–90 s
def test_building_bench_runs_on_a_tiny_floor(tmp_path):
  result = building.run(rooms=1, seed=0, height=24, width=32, voxel_size=0.1, num_frames=12,
                        stride=10, window=4, capacity=2**10, blocks=2**6, probe_frames=3,
                        reference=(2**12, 2**8))
  assert result["frames"] == 12 and result["voxels"] > 0 and result["dropped"] == 0
  assert result["growths"], "a map started this small must grow"
  assert result["windows"] and all(w["median_ms"] > 0 for w in result["windows"])
  last = result["checkpoints"][-1]
  # The probe (the first 3 frames fused again into a copy) runs once they are held and leaves
  # the map as it was: the read-out after it returns every voxel the walk put there.
  assert all((c["probe_ms"] is None) == (c["frame"] < 2) for c in result["checkpoints"])
  assert last["probe_ms"] > 0 and len(last["probe_ms_all"]) == 3 * building.PROBE_PASSES
  # Each probe frame also goes into a copy of the reference map, frame by frame beside it.
  probed = [c for c in result["checkpoints"] if c["probe_ms"] is not None]
  for c in probed:
    assert c["reference_ms"] > 0 and len(c["reference_ms_all"]) == len(c["probe_ms_all"])
    ratios = [a / b for a, b in zip(c["probe_ms_all"], c["reference_ms_all"])]
    assert min(ratios) <= c["relative"] <= max(ratios)
  assert result["reference"] == [2**12, 2**8]
  assert last["frame"] == 11 and last["read_voxels"] == result["voxels"]
  assert last["mesh_faces"] > 0 and last["query_points"] == building.NUM_QUERY
  assert result["per_voxel"]["semantic_per_slot"] > 0
  assert set(result["peers"]) == {"open3d_voxel_block_grid", "nvblox"}
  text = building.table(result)
  assert "| growth at frame |" in text and "nvblox" in text
  assert "reference map ms/frame (2^12 slots, 2^8 blocks)" in text
  json.dumps(result)                        # the record is JSON as written
  # The table-size check: the probe in a fresh map, nearly empty and filled by far voxels.
  rows = building.table_sizes(rooms=1, height=24, width=32, voxel_size=0.1,
                              sizes=((2**15, 2**8),), load=0.3)
  assert abs(rows[1]["load"] - rows[0]["load"] - 0.3) < 0.02      # the far voxels' share
  assert all(r["probe_ms"] > 0 for r in rows)
  # --table-sizes runs them in two processes: 4 KiB pages, then huge pages where offered.
  both = building.table_sizes_both(child_args=["--rooms", "1", "--height", "24", "--width",
                                               "32", "--voxel-size", "0.1",
                                               "--table-slots", "32768:256"])
  assert [r["pages"] for r in both][:2] == ["4 KiB", "4 KiB"] and len(both) in (2, 4)
  assert not both[0]["huge_pages"]["tunable"]
  if len(both) == 4:
    assert both[2]["pages"] == "huge" and both[2]["huge_pages"]["tunable"]
  assert [r["slots"] for r in both] == [2**15] * len(both)
  building.main(["--quick", "--rooms", "1", "--frames", "6", "--height", "24", "--width", "32",
                 "--out", str(tmp_path)])
  assert json.loads((tmp_path / "building_quick.json").read_text())["quick"] is True
  png = (tmp_path / "building_quick.png").read_bytes()
  assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000
