"""Several processes, one result (jaxfusion.distributed, lab.processes): two local processes
of one CPU device each, joined by JAX's distributed runtime, against one process; a process
that dies or never joins fails in bounded time with one line."""

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from jaxfusion import distributed
from jaxfusion.lab import cli
from jaxfusion.lab import processes
from tests.lab import distributed_worker

# End-to-end: joined processes of JAX's distributed runtime. The slow tier.
pytestmark = pytest.mark.slow

WORKER = os.path.join(os.path.dirname(os.path.abspath(__file__)), "distributed_worker.py")
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def test_fuse_batch_and_fuse_sweep_over_two_processes_equal_one_process_bit_for_bit(tmp_path):
  out = tmp_path / "two.npz"
  status = processes.launch(["fuse", str(out)], 2, program=[sys.executable, WORKER],
                            timeout_s=60)
  assert status == 0
  two = np.load(out)
  assert int(two["process_count"]) == 2 and int(two["num_devices"]) == 2
  # Every process got every process's object, in process order; items went every 2nd.
  assert str(two["objects"]) == repr([{"process": 0, "items": [0, 2, 4]},
                                      {"process": 1, "items": [1, 3]}])
  assert list(two["gathered"]) == [f"item {i}" for i in range(5)]
  one = distributed_worker.fuse(mesh=None)          # this process: one device, no runtime
  assert set(one) == {k for k in two.files if k.startswith(("batch_", "sweep_"))}
  for name, value in one.items():
    assert two[name].shape == value.shape, name
    np.testing.assert_array_equal(two[name], value, err_msg=name)
  assert one["batch_hits"].shape[0] == 3 and one["sweep_hits"].shape[0] == 3
  assert (one["batch_hits"].sum(axis=1) > 0).all()


def test_a_process_that_dies_stops_the_run_with_one_line_in_bounded_time(tmp_path, capfd):
  start = time.monotonic()
  status = processes.launch(["die", str(tmp_path / "x.npz")], 2,
                            program=[sys.executable, WORKER], name="worker", timeout_s=60)
  seconds = time.monotonic() - start
  err = capfd.readouterr().err.strip().splitlines()
  assert status == 2 and seconds < 60
  assert err[-1].startswith("worker: error: process 1 of 2 exited with status 3")
  assert "the other processes were stopped" in err[-1]


def test_a_process_that_comes_late_to_an_exchange_is_waited_for(tmp_path):
  # Past the 30 s in which gloo's collectives let processes meet, first process 1 then
  # process 0 comes late: the coordination service's barrier before each exchange waits.
  out = tmp_path / "late.npz"
  start = time.monotonic()
  status = processes.launch(["late", str(out)], 2, program=[sys.executable, WORKER],
                            timeout_s=60)
  assert status == 0 and time.monotonic() - start > 2 * distributed_worker.LATE_S
  late = np.load(out)
  assert list(late["gathered"]) == ["item 0", "item 1", "item 2"]
  np.testing.assert_array_equal(late["ones"], np.arange(4.0))


def test_a_barrier_that_a_process_never_reaches_fails_within_its_timeout(capfd):
  start = time.monotonic()
  status = processes.launch(["absent", "-"], 2, program=[sys.executable, WORKER],
                            name="worker", timeout_s=60)
  out, err = capfd.readouterr()
  assert status == 2 and time.monotonic() - start < 20
  assert err.strip().splitlines()[-1].startswith(
      "worker: error: process 0 of 2 exited with status 4")
  said = [line for line in out.splitlines() if line.startswith("DistributedError")]
  assert len(said) == 1, out
  assert said[0].startswith("DistributedError: process 0 of 2: not every process reached "
                            "'never reached' within 3 s: "), said[0]


def test_a_process_that_never_joins_fails_with_one_line_within_its_timeout():
  env = dict(os.environ, PYTHONPATH=ROOT)
  env.update({distributed.COORDINATOR_ENV: f"127.0.0.1:{processes.free_port()}",
              distributed.NUM_PROCESSES_ENV: "2", distributed.PROCESS_ID_ENV: "0",
              distributed.TIMEOUT_ENV: "4"})
  start = time.monotonic()
  run = subprocess.run([sys.executable, "-m", "jaxfusion.lab.cli", "sweep", "--num-betas", "2"],
                       env=env, capture_output=True, text=True, timeout=120, check=False)
  seconds = time.monotonic() - start
  assert run.returncode == 2 and seconds < 60
  last = run.stderr.strip().splitlines()[-1]
  assert last.startswith("jaxfusion sweep: error: could not join 2 processes at 127.0.0.1:")
  assert "within 4 s (process 0)" in last


def test_one_process_takes_every_item_and_gathers_them_in_order():
  assert distributed.process_count() == 1 and distributed.is_main()
  assert distributed.my_items(4) == [0, 1, 2, 3] and distributed.my_items(0) == []
  assert distributed.allgather_objects({"a": 1}) == [{"a": 1}]
  assert distributed.gather_items({1: "b", 0: "a"}, 2) == ["a", "b"]
  with pytest.raises(distributed.DistributedError, match=r"items \[2\] came from no process"):
    distributed.gather_items({0: "a", 1: "b"}, 3)


def test_launcher_and_environment_are_checked(monkeypatch, capsys):
  with pytest.raises(ValueError, match="--processes must be ≥ 1"):
    processes.launch([], 0)
  assert cli.main(["study", "--processes", "0"]) == 2
  assert "--processes must be ≥ 1; got 0" in capsys.readouterr().err
  monkeypatch.setenv(distributed.PROCESS_ID_ENV, "3")
  with pytest.raises(distributed.DistributedError, match="but not"):
    distributed.from_environment()
  monkeypatch.setenv(distributed.COORDINATOR_ENV, "127.0.0.1:1")
  monkeypatch.setenv(distributed.NUM_PROCESSES_ENV, "2")
  with pytest.raises(distributed.DistributedError, match=r"process id 3 does not lie in \[0, 2\)"):
    distributed.from_environment()
  monkeypatch.setenv(distributed.PROCESS_ID_ENV, "1")
  assert distributed.from_environment() == {"coordinator_address": "127.0.0.1:1",
                                            "num_processes": 2, "process_id": 1}


@pytest.mark.slow
def test_study_over_two_processes_writes_the_bytes_of_one_process(tmp_path):
  common = ["study", "--quick", "--resamples", "50", "--seeds", "1", "--frames", "3",
            "--height", "24", "--width", "32", "--num-samples", "3", "--shifts", "0", "1"]
  env = dict(os.environ, PYTHONPATH=ROOT)
  for name, extra in (("one", []), ("two", ["--processes", "2"])):
    run = subprocess.run([sys.executable, "-m", "jaxfusion.lab.cli", *common, "--out",
                          str(tmp_path / name), *extra], env=env, capture_output=True,
                         text=True, timeout=600, check=False)
    assert run.returncode == 0, run.stderr[-2000:]
  for name in ("study.json", "study.md", "study.csv", "miou_vs_shift.png",
               "differences_vs_shift.png", "headroom.png", "alpha_hist.png"):
    assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes(), name
  import json
  timing = json.loads((tmp_path / "two" / "timing.json").read_text())
  assert len(timing["processes"]) == 2 and len(timing["sequences"]) == 4
