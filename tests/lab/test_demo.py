"""The demo end to end on a tiny scene, its cache, and the CLI."""

import json
import os

import jax
import numpy as np
import pytest
import trimesh

import jaxfusion_models as models
from jaxfusion.lab import cli
from jaxfusion import datasets
from jaxfusion.lab import config as config_lib
from jaxfusion.lab import demo
from jaxfusion.lab import frontend

# The demo test below runs the `demo` command at these sizes (and its default capacity), so that
# both tests share one set of compiled shapes.
TINY = dict(envs=("office",), trajectories=(0,), num_frames=2, height=24, width=32,
            num_samples=2, capacity=config_lib.RunConfig.capacity)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
  """A tiny untrained network: the runner's plumbing does not need a good one."""
  config = models.tiny_config(len(datasets.CLASS_NAMES))
  # An RBG key compiles the initialiser in a fraction of threefry's time; any weights do.
  _, params = models.init(config, key=jax.random.key(0, impl="rbg"))
  path = tmp_path_factory.mktemp("ckpt") / "tiny.msgpack"
  models.save(path, params, config=config, class_names=datasets.CLASS_NAMES)
  return str(path)


@pytest.mark.slow
def test_runner_end_to_end_and_cache_reuse(tmp_path, checkpoint):
  config = config_lib.RunConfig(**TINY)
  out = demo.run_demo(config, str(tmp_path), checkpoint=checkpoint)
  table = out["table"].splitlines()
  for display in ("Sum probs", "Sum labels", "Bayesian", "| R |", "| D |", "D+R"):
    assert any(display in line for line in table), display
  with open(tmp_path / "results.json") as f:
    res = json.load(f)["results"]["all"]
  assert set(res) == {"Sum probs", "Sum labels", "Bayesian", "R", "D", "D+R"}
  for r in res.values():
    assert 0.0 <= r["accuracy"] <= 1.0 and len(r["iou"]) == len(datasets.CLASS_NAMES)
    assert np.sum(r["confusion"]) > 0
  for name in ("results.md", "results.csv", "iou_bars.png", "outlier.png",
               "maps_office_0_test.png"):
    assert (tmp_path / name).exists(), name
  ply = trimesh.load(str(tmp_path / "maps" / "office_0_test_robust_dr.ply"), process=False)
  assert len(ply.vertices) > 0
  caches = os.listdir(tmp_path / "cache")
  assert len(caches) == 1
  mtime = os.path.getmtime(tmp_path / "cache" / caches[0])
  again = demo.run_demo(config, str(tmp_path), checkpoint=checkpoint)
  assert os.path.getmtime(tmp_path / "cache" / caches[0]) == mtime   # reused, not recomputed
  assert again["table"] == out["table"]


@pytest.mark.slow
def test_cli_help_and_tiny_demo(tmp_path, checkpoint, capsys):
  with pytest.raises(SystemExit) as e:
    cli.main(["--help"])
  assert e.value.code == 0
  assert "demo" in capsys.readouterr().out
  rc = cli.main(["demo", "--out", str(tmp_path), "--checkpoint", checkpoint, "--frames", "2",
                 "--height", "24", "--width", "32", "--num-samples", "2", "--envs", "office",
                 "--trajectories", "1"])
  assert rc == 0
  printed = capsys.readouterr().out
  assert "D+R" in printed and "mIoU" in printed
  maps = sorted(os.listdir(tmp_path / "maps"))
  rc = cli.main(["export", "--map", str(tmp_path / "maps" / "office_1_test_bayes.npz"),
                 "--out", str(tmp_path / "bayes.ply"), "--mode", "points"])
  assert rc == 0 and (tmp_path / "bayes.ply").exists(), maps


@pytest.mark.parametrize("argv,message", [
    (["run", "--data", "nowhere:x"], "--data: a sequence is ENV:TRAJECTORY"),
    (["run", "--data", "scannet:/no/such/folder"], "no such folder"),
    (["run", "--data", "synthetic:office/7"], "--data: an embedded sequence is ENV:TRAJECTORY"),
    (["run", "--data", "office:0", "--layout-seeds", "1", "2"], "one --layout-seeds value"),
    (["run", "--data", "synthetic:office/0", "--rule", "kalman"], "unknown rule"),
    (["eval", "--map", "/no/map.npz", "--gt", "/no/gt.npz"], "no map file"),
    (["demo", "--frames", "0"], "--frames must be at least 1"),
])
def test_cli_bad_input_is_one_clear_line(argv, message, capsys):
  assert cli.main(argv) == 2
  err = capsys.readouterr().err
  assert message in err and "Traceback" not in err


def test_run_refuses_a_checkpoint_with_other_classes(tmp_path):
  config = models.tiny_config(3)
  _, params = models.init(config, key=jax.random.key(0, impl="rbg"))
  path = tmp_path / "three.msgpack"
  models.save(path, params, config=config, class_names=["a", "b", "c"])
  with pytest.raises(models.CheckpointError):
    frontend.FrontEnd(str(path))
