"""The viser viewer without a browser: its controls redraw what scene_data says, and the `view`
command binds to 127.0.0.1, serves the page, and stops cleanly on Ctrl-C."""

import os
import queue
import signal
import subprocess
import sys
import threading
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


# A 5 cm geometry layer for the floor: its ~4 × 3 m patch takes ~160 blocks of 40 cm.
GEOMETRY = jf.TSDFConfig(voxel_size=0.05, capacity=2**9)


def save_floor_maps(root, geometry=None) -> list:
  """Bayes and D+R maps of one floor frame (stripes of background, chair, plant, TV) with
  poses and a GT map beside them (and a geometry layer when `geometry`, a TSDFConfig, is
  given); returns the map paths. As in the demo, the geometry layer is fused once (with the
  first rule) and given to both maps: one compilation fewer."""
  frame = _plane_frame(len(NAMES))
  out, layer = [], None
  for name in ("bayes", "robust_dr"):
    rule = jf.rules.by_name(name)
    state = jf.init_map(capacity=4096, num_classes=len(NAMES), voxel_size=0.1, rule=rule,
                        geometry=geometry if layer is None else None)
    state = jf.fuse_frame(state, frame, CAMERA, rule)
    layer = state.geometry if layer is None else layer
    state = state.replace(geometry=layer)
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


@pytest.mark.slow
def test_view_command_serves_says_what_it_does_and_stops_on_ctrl_c(mesh_maps):
  env = dict(os.environ, PYTHONUNBUFFERED="1")
  # Started with SIGINT ignored, as a background job of a non-interactive shell is (and as
  # this test's parent may be after other tests): Ctrl-C must still stop the viewer.
  # (A tiny launcher ignores SIGINT and execs the command, which inherits the disposition.)
  launcher = ("import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_IGN); "
              "os.execv(sys.executable, [sys.executable, '-m', 'jaxfusion.lab.cli', 'view', "
              "*sys.argv[1:]])")
  path = mesh_maps[0].path
  proc = subprocess.Popen([sys.executable, "-c", launcher, path, "--port", "0"],
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
  printed = queue.Queue()   # lines read by a thread: a command that goes quiet fails the test

  def read_all():
    for line in proc.stdout:
      printed.put(line)
    printed.put(None)

  threading.Thread(target=read_all, daemon=True).start()

  def read_until(start):
    lines, deadline = [], time.monotonic() + 120
    while time.monotonic() < deadline:
      try:
        line = printed.get(timeout=max(deadline - time.monotonic(), 0.01))
      except queue.Empty:
        break
      if line is None:
        break
      lines.append(line.rstrip("\n"))
      if start in line:
        break
    return lines

  try:
    # It says what it loads, serves the page as soon as the voxels are loaded ...
    lines = read_until("viewing ")
    assert lines and lines[-1].startswith("viewing 1 map(s) of 1 sequence(s) at "
                                          "http://127.0.0.1:"), lines
    assert any(line.endswith(f"] loading {path} (1 of 1) …") for line in lines), lines
    url = lines[-1].split(" at ")[1].split()[0]
    with urllib.request.urlopen(url, timeout=10) as r:
      assert r.status == 200 and b"<html" in r.read(2000).lower()
    # ... and then prepares the mesh, one timed line per stage.
    lines = read_until("] ready: ")
    stages = [line.split("] ", 1)[1] for line in lines if line.startswith("[")]
    name = mesh_maps[0].name
    expected = ["preparing the mesh of 1 map(s)", f"{name}: preparing mesh: marching cubes on",
                f"{name}: preparing mesh: labelling", f"{name}: preparing mesh: GT labels",
                f"{name}: sending mesh: {mesh_maps[0].mesh.num_faces} faces …",
                "ready: 1 mesh(es) prepared in"]
    assert len(stages) == len(expected) and all(
        stage.startswith(want) for stage, want in zip(stages, expected)), lines
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=30)
    rest = "".join(iter(printed.get, None))
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


# Maps with a geometry layer: the mesh --------------------------------------------------------


@pytest.fixture(scope="module")
def mesh_maps(tmp_path_factory):
  return sd.load_maps(save_floor_maps(tmp_path_factory.mktemp("mesh_maps"), geometry=GEOMETRY))


def _record_glbs(viewer) -> list:
  """The GLB payloads the viewer sends from now on (`scene.add_glb` wrapped)."""
  sent, add_glb = [], viewer.server.scene.add_glb

  def recording(name, glb, **kwargs):
    sent.append((name, glb))
    return add_glb(name, glb, **kwargs)

  viewer.server.scene.add_glb = recording
  return sent


def _glb_faces(glb) -> int:
  import io as io_lib
  import trimesh
  scene = trimesh.load(io_lib.BytesIO(glb), file_type="glb", process=False)
  return sum(len(g.faces) for g in scene.geometry.values())


def test_show_switches_between_the_mesh_and_the_voxels(mesh_maps):
  bayes, dr = mesh_maps
  assert bayes.mesh is not None and bayes.mesh.num_faces > 0
  faces = bayes.mesh.num_faces
  viewer = server.MapViewer(mesh_maps, port=0)
  try:
    c = viewer.controls
    sent = _record_glbs(viewer)
    assert c["show"].visible and c["show"].options == ("mesh", "voxels", "mesh + voxels")
    # A map with a mesh opens on its mesh, every face of it, and no voxel.
    assert c["show"].value == "mesh"
    assert viewer.last_drawn == {"map": bayes.path, "mode": "class", "kind": None, "count": 0,
                                 "mesh": faces}
    assert not c["draw"].visible   # the voxels' control hides with them
    c["show"].value = "voxels"
    assert viewer.last_drawn == {"map": bayes.path, "mode": "class", "kind": "cubes",
                                 "count": len(bayes), "mesh": 0}
    assert c["draw"].visible and sent == []
    c["show"].value = "mesh + voxels"
    assert viewer.last_drawn == {"map": bayes.path, "mode": "class", "kind": "cubes",
                                 "count": len(bayes), "mesh": faces}
    assert [name for name, _ in sent] == ["/mesh"] and _glb_faces(sent[0][1]) == faces
    # The same mesh is not sent again for a redraw that does not change it.
    c["trajectory"].value = False
    assert len(sent) == 1
    # Hiding a class drops its faces (by the face's class) from the mesh and its voxels.
    k = int(np.bincount(bayes.mesh.face_labels[bayes.mesh.face_labels >= 0]).argmax())
    c["hide"][NAMES[k]].value = True
    kept = int(np.sum(bayes.mesh.face_labels != k))
    assert 0 < kept < faces
    assert viewer.last_drawn["mesh"] == kept == int(
        sd.mesh_face_mask(bayes, hidden_classes=[k]).sum())
    assert viewer.last_drawn["count"] == int(np.sum(bayes.labels != k))
    assert len(sent) == 2 and _glb_faces(sent[1][1]) == kept
    # A height cut below the floor (at z ≈ 0.05 m) leaves nothing.
    c["height"].value = c["height"].min
    assert c["height"].min < 0.04 and viewer.last_drawn["mesh"] == 0
    assert viewer.last_drawn["count"] == 0
  finally:
    viewer.stop()


def test_colour_modes_follow_what_is_shown(mesh_maps):
  bayes, dr = mesh_maps
  viewer = server.MapViewer(mesh_maps, port=0)
  try:
    c = viewer.controls
    sent = _record_glbs(viewer)
    gt, hits = sd.COLOR_MODES["correct"], sd.COLOR_MODES["hits"]
    alpha = sd.COLOR_MODES["confidence"]
    # Bayes: the mesh has a max posterior but no hit count; the voxels the reverse.
    assert c["color"].options == ("class", "entropy", "confidence (max posterior)", gt)
    c["show"].value = "voxels"
    assert c["color"].options == ("class", "entropy", hits, gt)
    c["show"].value = "mesh + voxels"
    assert c["color"].options == ("class", "entropy", gt)
    for show in sd.SHOW_CHOICES:
      c["show"].value = show
      assert c["color"].options == tuple(sd.mode_titles(bayes, show).values())
    # D+R: ᾱ on the voxels; the mode is kept when what is shown changes, under its new title.
    c["map"].value = dr.name
    c["show"].value = "voxels"
    c["color"].value = alpha
    assert viewer.last_drawn["mode"] == "confidence" and viewer.last_drawn["mesh"] == 0
    del sent[:]
    c["show"].value = "mesh"
    assert c["color"].value == "confidence (max posterior)"
    assert viewer.last_drawn == {"map": dr.path, "mode": "confidence", "kind": None,
                                 "count": 0, "mesh": dr.mesh.num_faces}
    assert len(sent) == 1   # drawn once, in the mode kept (not first in class)
    c["show"].value = "mesh + voxels"
    assert c["color"].value == "confidence (mesh: max posterior, voxels: ᾱ)"
    assert viewer.last_drawn["mode"] == "confidence" and viewer.last_drawn["count"] == len(dr)
    # Bayes has no ᾱ: with both layers shown its colour falls back to class.
    c["map"].value = bayes.name
    assert viewer.last_drawn["mode"] == "class" and c["color"].value == "class"
    c["color"].value = gt
    assert viewer.last_drawn["mode"] == "correct"
  finally:
    viewer.stop()


def test_maps_without_a_mesh_show_their_voxels(maps, mesh_maps):
  import dataclasses
  plain = [dataclasses.replace(m, sequence="plain", path=m.path + "#plain") for m in maps]
  viewer = server.MapViewer([*mesh_maps, *plain], port=0)
  try:
    c = viewer.controls
    assert c["show"].visible and c["show"].value == "mesh"
    c["sequence"].value = "plain"
    assert viewer.last_drawn == {"map": plain[0].path, "mode": "class", "kind": "cubes",
                                 "count": len(plain[0])}   # no "mesh": this map has none
    assert c["color"].options == tuple(sd.COLOR_MODES[m] for m in sd.color_modes(plain[0]))
  finally:
    viewer.stop()
  viewer = server.MapViewer(maps, port=0)
  try:
    assert not viewer.controls["show"].visible and viewer.controls["show"].value == "voxels"
  finally:
    viewer.stop()


# Meshes made in the background ---------------------------------------------------------------


def _record_removals(viewer) -> list:
  """The scene nodes the viewer removes from now on (`scene.remove_by_name` wrapped)."""
  removed, remove = [], viewer.server.scene.remove_by_name

  def recording(name):
    removed.append(name)
    return remove(name)

  viewer.server.scene.remove_by_name = recording
  return removed


def test_meshes_are_prepared_in_the_background_and_say_so(mesh_maps):
  pending = sd.load_maps([m.path for m in mesh_maps], mesh=False)
  bayes, dr = pending
  lines = []
  viewer = server.MapViewer(pending, port=0, preview_voxels=200, progress=lines.append,
                            prepare=False)
  try:
    c = viewer.controls
    sent, removed = _record_glbs(viewer), _record_removals(viewer)
    # Before the meshes are there: the controls of a map with a mesh, and in the mesh's place
    # the coarse preview of its voxels.
    assert viewer.ready.is_set() is False and viewer.progress == []
    assert c["show"].visible and c["show"].value == "mesh"
    assert c["color"].options == tuple(sd.mode_titles(mesh_maps[0], "mesh").values())
    preview = sd.coarse_voxels(bayes, max_voxels=200)
    assert 0 < len(preview) <= 200 < len(bayes)
    assert viewer.last_drawn == {"map": bayes.path, "mode": "class", "kind": None, "count": 0,
                                 "mesh": 0, "preview": len(preview)}
    c["show"].value = "voxels"   # the voxels themselves when asked for
    assert viewer.last_drawn == {"map": bayes.path, "mode": "class", "kind": "cubes",
                                 "count": len(bayes), "mesh": 0, "preview": 0}
    c["show"].value = "mesh"
    viewer.prepare_meshes()
    viewer.prepare_meshes()   # once only
    assert viewer.ready.wait(120)
    # The full mesh replaced the preview, the same as made at load; the other map's is made too.
    faces = mesh_maps[0].mesh.num_faces
    assert viewer.last_drawn == {"map": bayes.path, "mode": "class", "kind": None, "count": 0,
                                 "mesh": faces}
    assert [name for name, _ in sent] == ["/mesh"] and _glb_faces(sent[0][1]) == faces
    assert "/preview" in removed
    for got, want in zip(viewer.current_map().mesh, mesh_maps[0].mesh):
      np.testing.assert_array_equal(got, want)
    c["map"].value = dr.name
    assert viewer.last_drawn["mesh"] == mesh_maps[1].mesh.num_faces
    assert "preview" not in viewer.last_drawn
    # What it said, in order, to the callback as to the panel's line: the shown map first.
    assert lines == viewer.progress
    expected = ["preparing the mesh of 2 map(s); a coarse preview of the voxels is shown "
                "meanwhile …"]
    for i, m in enumerate(mesh_maps):
      what = f"{m.name} ({i + 1} of 2)"
      expected += [f"{what}: preparing mesh: marching cubes on",
                   f"{what}: preparing mesh: labelling {m.mesh.num_vertices} vertices",
                   f"{what}: preparing mesh: GT labels of {m.mesh.num_vertices} vertices",
                   f"{what}: sending mesh: {m.mesh.num_faces} faces …"]
    expected.append("ready: 2 mesh(es) prepared in ")
    assert len(lines) == len(expected) and all(
        line.startswith(want) for line, want in zip(lines, expected)), lines
  finally:
    viewer.stop()


def test_a_mesh_that_cannot_be_made_is_said_and_its_voxels_shown(mesh_maps):
  import dataclasses
  (m,) = sd.load_maps([mesh_maps[0].path], mesh=False)
  broken = dataclasses.replace(m, mesh_source=sd.MeshSource(state=None))
  viewer = server.MapViewer([broken], port=0)
  try:
    assert viewer.ready.wait(60)
    assert viewer.progress[-2].startswith(f"{m.name}: preparing the mesh failed: "
                                          "AttributeError")
    assert viewer.progress[-1].startswith("ready: 0 mesh(es) prepared in ")
    assert "1 failed, the first: " + viewer.progress[-2] in viewer.progress[-1]
    assert viewer.last_drawn == {"map": m.path, "mode": "class", "kind": "cubes",
                                 "count": len(m)}   # no mesh: its voxels
  finally:
    viewer.stop()
