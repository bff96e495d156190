"""The viser viewer without a browser: its controls redraw what scene_data says, and the `view`
command binds to 127.0.0.1, serves the page, and stops cleanly on Ctrl-C."""

import os
import signal
import subprocess
import sys
import time
import urllib.request

import numpy as np
import pytest

pytest.importorskip("viser")

import jaxfusion as jf   # noqa: E402
from jaxfusion import datasets, io   # noqa: E402
from jaxfusion.lab.viewer import scene_data as sd   # noqa: E402
from jaxfusion.lab.viewer import server   # noqa: E402

NAMES = tuple(datasets.CLASS_NAMES)
CAMERA = jf.Camera(24.0, 24.0, 23.5, 17.5)
SIZE = (36, 48)


def _plane_frame(num_classes, height=SIZE[0], width=SIZE[1]):
  """A camera 2 m above a floor, looking down; the image split into class stripes."""
  T = np.diag([1.0, -1.0, -1.0, 1.0]).astype(np.float32)
  T[2, 3] = 2.0
  labels = (np.arange(width)[None, :] * 4 // width + np.zeros((height, 1), int)) * 2
  probs = 0.1 / num_classes + 0.9 * np.eye(num_classes, dtype=np.float32)[labels]
  probs /= probs.sum(-1, keepdims=True)
  var = np.full(probs.shape, 0.01, np.float32)
  return jf.Frame(np.full((height, width), 1.95, np.float32), T, probs.astype(np.float32), var)


def save_floor_maps(root) -> list:
  """Bayes and D+R maps of one floor frame (stripes of background, chair, plant, TV) with
  poses and a GT map beside them; returns the map paths."""
  frame = _plane_frame(len(NAMES))
  out = []
  for name in ("bayes", "robust_dr"):
    rule = jf.rules.by_name(name)
    state = jf.init_map(capacity=4096, num_classes=len(NAMES), voxel_size=0.1, rule=rule)
    state = jf.fuse_frame(state, frame, CAMERA, rule)
    path = str(root / f"floor_{name}.npz")
    io.save_map(path, state, rule, class_names=NAMES, extra={"sequence": "floor"},
                poses=np.stack([frame.T_world_cam] * 3), camera=CAMERA, image_size=SIZE)
    out.append(path)
  voxels = jf.read_map(state)
  np.savez(root / "floor_gt.npz", coords=voxels["coords"],
           labels=np.where(voxels["labels"] == 0, 0, 1).astype(np.int32))
  return out


@pytest.fixture(scope="module")
def maps(tmp_path_factory):
  return sd.load_maps(save_floor_maps(tmp_path_factory.mktemp("maps")))


def test_controls_redraw_the_scene(maps):
  viewer = server.MapViewer(maps, port=0)
  try:
    c = viewer.controls
    bayes, dr = maps
    assert viewer.url.startswith("http://127.0.0.1:")
    assert viewer.last_drawn == {"map": bayes.path, "mode": "class", "kind": "cubes",
                                 "count": len(bayes)}
    # Bayes has no ᾱ: the colour control offers what this map has.
    assert c["color"].options == ("class", "entropy", "hit count", "right / wrong vs GT")
    c["color"].value = "entropy"
    assert viewer.last_drawn["mode"] == "entropy"
    c["map"].value = dr.name   # the mode is kept across maps when the new map has it
    assert viewer.last_drawn["map"] == dr.path and viewer.last_drawn["mode"] == "entropy"
    assert sd.COLOR_MODES["confidence"] in c["color"].options
    c["color"].value = sd.COLOR_MODES["confidence"]
    assert viewer.last_drawn["mode"] == "confidence"
    c["map"].value = bayes.name   # ... and falls back to class when it has not
    assert viewer.last_drawn["mode"] == "class" and c["color"].value == "class"
    # Hiding classes and cutting the height draw what visible_mask keeps.
    present = sorted(set(bayes.labels.tolist()))
    c["hide"][NAMES[present[0]]].value = True
    expected = int(sd.visible_mask(bayes, hidden_classes=[present[0]]).sum())
    assert 0 < viewer.last_drawn["count"] == expected < len(bayes)
    c["height"].value = c["height"].min
    assert viewer.last_drawn["count"] == int(sd.visible_mask(
        bayes, hidden_classes=[present[0]], max_height=c["height"].min).sum())
    c["height"].value = c["height"].max
    c["draw"].value = "points"
    assert viewer.last_drawn["kind"] == "points" and viewer.last_drawn["count"] == expected
    c["trajectory"].value = False
  finally:
    viewer.stop()


def test_large_maps_are_drawn_as_points(maps):
  viewer = server.MapViewer(maps[:1], port=0, max_cubes=len(maps[0]) - 1)
  try:
    assert viewer.last_drawn["kind"] == "points"
    assert not viewer.controls["sequence"].visible   # one sequence: no sequence control
  finally:
    viewer.stop()


def test_view_command_serves_and_stops_on_ctrl_c(maps):
  env = dict(os.environ, PYTHONUNBUFFERED="1")
  # Started with SIGINT ignored, as a background job of a non-interactive shell is (and as
  # this test's parent may be after other tests): Ctrl-C must still stop the viewer.
  # (A tiny launcher ignores SIGINT and execs the command, which inherits the disposition.)
  launcher = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
              "os.execv(sys.executable, [sys.executable, '-m', 'jaxfusion.lab.cli', 'view', "
              "*sys.argv[1:]])")
  proc = subprocess.Popen([sys.executable, "-c", launcher, maps[0].path, "--port", "0"],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
  try:
    lines = []
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
      line = proc.stdout.readline()
      if not line:
        break
      lines.append(line)
      if line.startswith("viewing "):
        break
    assert lines and lines[-1].startswith("viewing 1 map(s) of 1 sequence(s) at "
                                          "http://127.0.0.1:"), lines
    url = lines[-1].split(" at ")[1].split()[0]
    with urllib.request.urlopen(url, timeout=10) as r:
      assert r.status == 200 and b"<html" in r.read(2000).lower()
    proc.send_signal(signal.SIGINT)
    rest, _ = proc.communicate(timeout=30)
    assert proc.returncode == 0, rest
    assert "viewer stopped" in rest and "Traceback" not in rest
  finally:
    if proc.poll() is None:
      proc.kill()
      proc.wait()


def test_sequence_control_switches_between_sequences(maps):
  import dataclasses
  other = [dataclasses.replace(m, sequence="hall", path=m.path + "#hall") for m in maps]
  viewer = server.MapViewer([*maps, other[1]], port=0)
  try:
    c = viewer.controls
    assert c["sequence"].visible and c["sequence"].options == ("floor", "hall")
    c["map"].value = maps[1].name
    c["sequence"].value = "hall"   # the same map name exists there: it is kept
    assert c["map"].options == (other[1].name,)
    assert viewer.last_drawn["map"] == other[1].path
    c["sequence"].value = "floor"
    assert viewer.last_drawn["map"] == maps[1].path
    c["map"].value = maps[0].name
    c["sequence"].value = "hall"   # Bayesian is not there: its only map is shown
    assert c["map"].value == other[1].name and viewer.last_drawn["map"] == other[1].path
  finally:
    viewer.stop()
