"""The growth bench (bench.growth) on a few small frames: one configuration's record, and the
compile costs of a growth's programs. No timings are asserted: `python -m bench.growth`
measures them."""

import json
import os
import pathlib
import subprocess
import sys

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


@pytest.mark.slow   # a process of its own (it moves its threads between CPUs): ~15 s
def test_steady_loops_with_the_host_apart_write_their_record(tmp_path):
  done = subprocess.run([sys.executable, "-m", "bench.growth", "--steady", "--quick",
                         "--host-apart", "--out", str(tmp_path)], capture_output=True,
                        text=True, check=False, cwd=pathlib.Path(growth.__file__).parent.parent)
  if len(os.sched_getaffinity(0)) < 2:
    assert done.returncode != 0 and "needs at least 2 CPUs" in done.stderr
    return
  assert done.returncode == 0, done.stderr
  record = json.loads((tmp_path / "growth_steady_apart_quick.json").read_text())
  assert record["host_apart"] is True and record["turns"] == 4
  assert set(record["median_ms"]) == {"mapper_plain", "fuse_frame_plain", "mapper_waiting",
                                      "fuse_frame_waiting"}
  assert all(len(v) == 4 and min(v) > 0 for v in record["turn_ms"].values())
  assert "| plain |" in done.stdout and "host apart" in done.stdout
