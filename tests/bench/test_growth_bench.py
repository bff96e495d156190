"""The growth bench (bench.growth) on a few small frames: one configuration's record, and the
compile costs of a growth's programs. No timings are asserted: `python -m bench.growth`
measures them."""

import json

import pytest

from bench import growth


@pytest.mark.slow   # each program compiled afresh, and one short walk: ~20–40 s
def test_growth_bench_records_a_walk_and_each_program_a_growth_compiles(tmp_path):
  run = growth.run_one(40, 24, 32, 4)
  assert run["voxels"] > 0 and run["dropped"] == 0 and run["growth_factor"] == 4
  assert len(run["growth_frames"]) == len({t for t, _, _ in run["semantic_growths"]
                                           + run["geometry_growths"] if t > 0})
  assert run["fuse_s"] > 0 and run["fixed_s"] > 0 and run["growth_share"] < 1
  growth.main(["--compiles", "--quick", "--out", str(tmp_path)])
  record = json.loads((tmp_path / "growth_compiles_quick.json").read_text())
  names = [r["program"] for r in record["programs"]]
  assert len(names) == 8 and names[0].startswith("prepare_frame")
  assert any(name.startswith("fuse_frame, both layers") for name in names)
  # Each program was compiled afresh (a program reused from memory takes no time at all).
  assert all(r["compile_s"] > 0.005 for r in record["programs"]), record
