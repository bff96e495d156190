"""The viewer's pure parts: finding and loading maps, colours per mode, legend, filters, and the
`view` command's one-line errors. No browser and no viser needed."""

import dataclasses
import io as io_lib
import os
import sys

import matplotlib
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion.lab import cli
from jaxfusion import io
from jaxfusion import mesh as mesh_lib
from jaxfusion.lab.viewer import scene_data as sd
from tests import engine_helpers as h

# End-to-end: each test prepares a viewer scene from maps fused by `jaxfusion run`. The slow tier.
pytestmark = pytest.mark.slow

NAMES = ("wall", "chair", "table", "plant")


def _view_map(labels, *, centers=None, hits=None, entropy=None, confidence=None,
              gt_labels=None, names=NAMES):
  labels = np.asarray(labels, np.int32)
  n = len(labels)
  return sd.ViewMap(
      path="m.npz", name="m", sequence="s", class_names=tuple(names), voxel_size=0.1,
      centers=np.zeros((n, 3), np.float32) if centers is None else np.asarray(centers,
                                                                               np.float32),
      labels=labels, hits=np.ones(n, np.int32) if hits is None else np.asarray(hits, np.int32),
      entropy=np.zeros(n, np.float32) if entropy is None else np.asarray(entropy, np.float32),
      confidence=None if confidence is None else np.asarray(confidence, np.float32),
      gt_labels=None if gt_labels is None else np.asarray(gt_labels, np.int32))


def _viridis(t):
  return np.round(np.asarray(matplotlib.colormaps["viridis"](np.asarray(t)))[:, :3] * 255)


def test_class_colours_and_legend():
  palette = np.array([[1, 2, 3], [10, 20, 30], [200, 0, 0], [0, 200, 0]], np.uint8)
  m = _view_map([2, 0, 2, 3])
  np.testing.assert_array_equal(sd.voxel_colors(m, "class", palette),
                                [[200, 0, 0], [1, 2, 3], [200, 0, 0], [0, 200, 0]])
  assert sd.legend(m, "class", palette) == [
      ("wall (1)", (1, 2, 3)), ("chair (0)", (10, 20, 30)), ("table (2)", (200, 0, 0)),
      ("plant (1)", (0, 200, 0))]
  with pytest.raises(ValueError, match="palette"):
    sd.voxel_colors(m, "class", palette[:3])
  with pytest.raises(ValueError, match="colour mode"):
    sd.voxel_colors(m, "rainbow", palette)


def test_entropy_uses_a_fixed_scale_of_log_k():
  k = len(NAMES)
  entropy = np.array([0.0, np.log(k) / 2, np.log(k), 2 * np.log(k)])   # last: clipped
  m = _view_map([0, 1, 2, 3], entropy=entropy)
  got = sd.voxel_colors(m, "entropy", None)
  np.testing.assert_allclose(got, _viridis([0.0, 0.5, 1.0, 1.0]), atol=1)
  np.testing.assert_array_equal(got[0], (68, 1, 84))     # viridis' ends, by hand
  np.testing.assert_array_equal(got[2], (253, 231, 37))
  texts = [t for t, _ in sd.legend(m, "entropy", None)]
  assert texts[0] == "0 nats" and texts[-1] == f"{np.log(k):.3g} nats"


def test_hits_and_confidence_use_a_log_scale_over_the_map():
  m = _view_map([0, 0, 0], hits=[1, 10, 100], confidence=[2.0, 20.0, 200.0])
  for mode in ("hits", "confidence"):
    t, lo, hi, _ = sd.scalar_field(m, mode)
    np.testing.assert_allclose(t, [0.0, 0.5, 1.0], atol=1e-6)
    np.testing.assert_allclose(sd.voxel_colors(m, mode, None), _viridis([0.0, 0.5, 1.0]),
                               atol=1)
  assert sd.scalar_field(m, "hits")[1:3] == (1.0, 100.0)
  texts = [t for t, _ in sd.legend(m, "hits", None)]
  assert texts[0] == "1 pixels" and texts[2] == "10 pixels" and texts[-1] == "100 pixels"
  flat = _view_map([0, 1], hits=[5, 5])
  np.testing.assert_array_equal(sd.scalar_field(flat, "hits")[0], [0.0, 0.0])


def test_modes_depend_on_what_the_map_has():
  palette = sd.class_palette(NAMES)
  plain = _view_map([0, 1])
  assert sd.color_modes(plain) == ("class", "entropy", "hits")
  with pytest.raises(ValueError, match="no Dirichlet confidence"):
    sd.voxel_colors(plain, "confidence", palette)
  with pytest.raises(ValueError, match="no GT"):
    sd.voxel_colors(plain, "correct", palette)
  full = _view_map([0, 1], confidence=[1.0, 2.0], gt_labels=[0, 0])
  assert sd.color_modes(full) == tuple(sd.COLOR_MODES)


def test_right_wrong_against_gt():
  m = _view_map([0, 1, 2, 3, 3], gt_labels=[-1, 1, 0, 3, 2])
  np.testing.assert_array_equal(
      sd.voxel_colors(m, "correct", None),
      [sd.UNSCORED_COLOR, sd.RIGHT_COLOR, sd.WRONG_COLOR, sd.RIGHT_COLOR, sd.WRONG_COLOR])
  assert [t for t, _ in sd.legend(m, "correct", None)] == [
      "right (2, accuracy 50.0 %)", "wrong (2)", "not in GT (1)"]


def test_visible_mask_hides_classes_and_cuts_height():
  centers = [[0, 0, 0.1], [0, 0, 1.0], [0, 0, 2.5], [5, 5, 0.0]]
  m = _view_map([0, 1, 1, 2], centers=centers)
  np.testing.assert_array_equal(sd.visible_mask(m), [True] * 4)
  np.testing.assert_array_equal(sd.visible_mask(m, hidden_classes=[1]), [1, 0, 0, 1])
  np.testing.assert_array_equal(sd.visible_mask(m, max_height=1.0), [1, 1, 0, 1])
  np.testing.assert_array_equal(sd.visible_mask(m, hidden_classes={0, 2}, max_height=2.0),
                                [0, 1, 0, 0])
  np.testing.assert_array_equal(sd.visible_mask(m, max_height=0.0, up_axis=0), [1, 1, 1, 0])
  with pytest.raises(ValueError, match="hidden classes"):
    sd.visible_mask(m, hidden_classes=[4])


def test_cubes_up_to_the_threshold_then_points():
  assert sd.representation(10, 10) == "cubes"
  assert sd.representation(11, 10) == "points"
  assert sd.representation(0, 0) == "cubes"
  assert sd.representation(10**6, 200_000) == "points"
  assert sd.representation(10**6, 0, "cubes") == "cubes"
  assert sd.representation(1, 10, "points") == "points"
  with pytest.raises(ValueError):
    sd.representation(1, -1)
  with pytest.raises(ValueError, match="choice"):
    sd.representation(1, 1, "spheres")


def test_legend_html_escapes_names():
  out = sd.legend_html([("<b>sofa</b> & co", (1, 2, 3))])
  assert "&lt;b&gt;sofa&lt;/b&gt; &amp; co" in out and "rgb(1,2,3)" in out
  assert "<b>" not in out


def test_camera_frustums_and_start_view():
  np.testing.assert_array_equal(sd.frustum_indices(5, 10), np.arange(5))
  np.testing.assert_array_equal(sd.frustum_indices(100, 3), [0, 50, 99])
  with pytest.raises(ValueError):
    sd.frustum_indices(3, 0)
  fov, aspect = sd.frustum_shape({"fx": 50.0, "fy": 50.0, "cx": 0, "cy": 0, "height": 100,
                                  "width": 160})
  assert fov == pytest.approx(np.pi / 2) and aspect == pytest.approx(1.6)
  assert sd.frustum_shape(None) == pytest.approx((np.pi / 3, 4 / 3))
  m = _view_map([0, 0], centers=[[0, 0, 0], [4, 2, 2]])
  position, look_at = sd.initial_camera([m])
  np.testing.assert_allclose(look_at, [2, 1, 1])
  assert position[2] > look_at[2]   # from above
  assert sd.height_range([m]) == (0.0, 2.0)


# Saved maps (made with the engine) ---------------------------------------------------------


def _save(path, name, *, class_names=NAMES, seed=0, sequence="seqA", poses=True):
  rng = np.random.default_rng(seed)
  rule = jf.rules.by_name(name, **h.rule_kwargs(name, beta=0.25))
  state = jf.init_map(capacity=256, num_classes=len(class_names), voxel_size=0.25, rule=rule)
  T = [h.pose(rng) for _ in range(2)]
  for t in range(2):
    state = jf.fuse_frame(state, h.random_frame(rng, num_classes=len(class_names), T=T[t]),
                          h.CAMERA, rule)
  kwargs = dict(poses=np.stack(T), camera=h.CAMERA, image_size=(h.HEIGHT, h.WIDTH)) if poses \
      else {}
  io.save_map(str(path), state, rule, class_names=class_names, extra={"sequence": sequence},
              **kwargs)
  return jf.read_map(state)


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory):
  """A folder laid out like the demo's output: maps/, GT labels, a cache of other .npz."""
  root = tmp_path_factory.mktemp("demo")
  (root / "maps").mkdir()
  (root / "cache").mkdir()
  voxels = {name: _save(root / "maps" / f"seqA_{name}.npz", name)
            for name in ("bayes", "robust_dr")}
  coords = voxels["bayes"]["coords"]
  gt = {"coords": coords[::2], "labels": (coords[::2, 0] % 4).astype(np.int32)}
  np.savez(root / "maps" / "seqA_gt.npz", **gt)
  np.savez(root / "cache" / "seqA__model-x.npz", det=np.zeros(3))
  (root / "results.md").write_text("| table |")
  return root, voxels, gt


def test_folder_finds_maps_and_gt_and_skips_other_files(run_folder):
  root, voxels, gt = run_folder
  files = sd.find_map_files([str(root)])
  assert [os.path.basename(f) for f in files] == ["seqA_bayes.npz", "seqA_robust_dr.npz"]
  maps = sd.load_maps([str(root), files[0]])   # the same file twice is shown once
  assert [m.name for m in maps] == ["Bayesian", "D+R β=0.25"]
  assert sd.by_sequence(maps).keys() == {"seqA"}
  bayes, dr = maps
  np.testing.assert_array_equal(bayes.labels, voxels["bayes"]["labels"])
  np.testing.assert_allclose(bayes.centers, voxels["bayes"]["centers"])
  assert bayes.confidence is None and dr.confidence is not None
  ref = voxels["robust_dr"]
  np.testing.assert_array_equal(dr.confidence,
                                [ref["confidence"][i, ref["labels"][i]] for i in range(len(dr))])
  # GT label per voxel, by an independent dictionary lookup.
  table = {tuple(c): l for c, l in zip(gt["coords"].tolist(), gt["labels"].tolist())}
  expected = [table.get(tuple(c), -1) for c in voxels["bayes"]["coords"].tolist()]
  np.testing.assert_array_equal(bayes.gt_labels, expected)
  assert (bayes.gt_labels == -1).sum() == len(bayes) - len(gt["coords"])
  assert bayes.poses.shape == (2, 4, 4) and bayes.camera["width"] == h.WIDTH
  assert bayes.class_names == NAMES


def test_run_layout_gt_and_maps_without_poses(tmp_path):
  _save(tmp_path / "seq_bayes.npz", "bayes", poses=False)
  voxels = _save(tmp_path / "other_bayes.npz", "bayes", seed=1, sequence="seqB")
  np.savez(tmp_path / "other_bayes_gt.npz", coords=voxels["coords"], labels=voxels["labels"])
  maps = {m.sequence: m for m in sd.load_maps([str(tmp_path)])}
  assert maps["seqA"].poses is None and maps["seqA"].gt_labels is None
  np.testing.assert_array_equal(maps["seqB"].gt_labels, voxels["labels"])
  np.testing.assert_array_equal(
      sd.voxel_colors(maps["seqB"], "correct", None),
      np.broadcast_to(sd.RIGHT_COLOR, (len(voxels["labels"]), 3)))


def test_same_rule_twice_gets_told_apart(tmp_path):
  for folder in ("a", "b"):
    (tmp_path / folder).mkdir()
    _save(tmp_path / folder / f"{folder}_bayes.npz", "bayes")
  names = [m.name for m in sd.load_maps([str(tmp_path)])]
  assert names == ["Bayesian [a_bayes.npz]", "Bayesian [b_bayes.npz]"]


def test_a_cleared_map_shows_what_it_reads_out(tmp_path):
  rule = jf.rules.bayes()
  state = jf.init_map(capacity=256, num_classes=len(NAMES), voxel_size=0.25, rule=rule,
                      free_space=jf.FreeSpaceConfig(prob_miss=0.2))
  probs = np.full((h.HEIGHT, h.WIDTH, len(NAMES)), 1 / len(NAMES), np.float32)
  for z in (1.1, 3.1):            # a wall, then one behind it seen through the first
    depth = np.full((h.HEIGHT, h.WIDTH), z, np.float32)
    state = jf.fuse_frame(state, jf.Frame(depth, np.eye(4, dtype=np.float32), probs), h.CAMERA,
                          rule)
  io.save_map(str(tmp_path / "seqA_bayes.npz"), state, rule, class_names=NAMES,
              extra={"sequence": "seqA"})
  (m,) = sd.load_maps([str(tmp_path)])
  stats = jf.map_stats(state)
  assert m.name == "Bayesian + free space" and stats["free"] > 0
  assert len(m.labels) == stats["occupied"] - stats["free"]
  np.testing.assert_allclose(m.centers, jf.read_map(state)["centers"])


def test_bad_inputs_raise_one_clear_error(tmp_path, run_folder):
  root, _, _ = run_folder
  with pytest.raises(FileNotFoundError, match="no such file or folder"):
    sd.find_map_files([str(tmp_path / "nope")])
  with pytest.raises(ValueError, match="not a jaxfusion map"):
    sd.find_map_files([str(root / "maps" / "seqA_gt.npz")])
  with pytest.raises(ValueError, match="not a jaxfusion map"):
    sd.find_map_files([str(root / "results.md")])
  np.save(tmp_path / "array.npy", np.zeros(3))
  with pytest.raises(ValueError, match="not a jaxfusion map"):
    sd.find_map_files([str(tmp_path / "array.npy")])
  (tmp_path / "empty").mkdir()
  with pytest.raises(ValueError, match="no jaxfusion map"):
    sd.find_map_files([str(tmp_path / "empty")])
  with pytest.raises(ValueError, match="at least one"):
    sd.find_map_files([])
  _save(tmp_path / "three.npz", "bayes", class_names=("a", "b", "c", "d"))
  with pytest.raises(ValueError, match="different class lists"):
    sd.load_maps([str(root), str(tmp_path / "three.npz")])


@pytest.mark.parametrize("which, message", [
    ("missing", "no such file or folder"),
    ("not_a_map", "is not a jaxfusion map file"),
    ("classes", "different class lists"),
])
def test_view_command_errors_are_one_line_exit_2(tmp_path, run_folder, capsys, which, message):
  root, _, _ = run_folder
  paths = {"missing": [str(tmp_path / "nope.npz")],
           "not_a_map": [str(root / "results.md")],
           "classes": [str(root), str(tmp_path / "other.npz")]}[which]
  if which == "classes":
    _save(tmp_path / "other.npz", "bayes", class_names=("a", "b", "c", "d"))
  pytest.importorskip("viser")
  assert cli.main(["view", *paths, "--port", "0"]) == 2
  err = capsys.readouterr().err
  assert err.startswith("jaxfusion view: error: ") and message in err
  assert err.count("\n") == 1


def test_view_without_viser_says_what_to_install(run_folder, capsys, monkeypatch):
  root, _, _ = run_folder
  monkeypatch.setitem(sys.modules, "viser", None)   # `import viser` now raises ImportError
  assert cli.main(["view", str(root)]) == 2
  err = capsys.readouterr().err
  assert "pip install 'jaxfusion[viewer]'" in err and err.count("\n") == 1
  assert cli.main(["view", str(root), "--port", "70000"]) == 2
  assert "--port" in capsys.readouterr().err
  for host in ("192.0.2.1",):   # not an address of this machine: one line, no endless wait
    assert cli.main(["view", str(root), "--host", host]) == 2
    err = capsys.readouterr().err
    assert "--host" in err and err.count("\n") == 1


@pytest.fixture(scope="module")
def run_output(tmp_path_factory):
  """`(sequence, folder)`: a `jaxfusion run` of 3 synthetic frames (with its geometry layer)."""
  from jaxfusion import datasets, sources
  tmp_path = tmp_path_factory.mktemp("run")
  seq = datasets.make_sequence("office", 0, num_frames=3, height=24, width=32)
  k = len(seq.class_names)
  for t in range(len(seq)):   # predictions: the GT labels, softened
    probs = 0.2 / k + 0.8 * np.eye(k, dtype=np.float32)[np.maximum(seq.labels[t], 0)]
    sources.save_prediction(tmp_path / "pred" / f"{t:06d}.npz", mean=probs)
  out = tmp_path / "run"
  # Sizes and capacity of tests/lab/test_study.py and test_demo.py: compiled steps are shared.
  assert cli.main(["run", "--data", "synthetic:office/0", "--frames", "3", "--height", "24",
                   "--width", "32", "--rule", "bayes", "--predictions", str(tmp_path / "pred"),
                   "--capacity", "131072", "--out", str(out)]) == 0
  return seq, out


def test_maps_from_jaxfusion_run_carry_poses_and_gt(run_output):
  seq, out = run_output
  (m,) = sd.load_maps([str(out)])
  assert m.sequence == seq.name and m.class_names == tuple(seq.class_names)
  np.testing.assert_array_equal(m.poses, seq.T_world_cam)
  assert m.camera == {"fx": seq.camera.fx, "fy": seq.camera.fy, "cx": seq.camera.cx,
                      "cy": seq.camera.cy, "height": 24, "width": 32}
  assert m.gt_labels is not None and np.mean(m.gt_labels >= 0) > 0.9
  assert "correct" in sd.color_modes(m)


# The mesh (a hand-made one) ----------------------------------------------------------------

# Five vertices, three faces; vertex 2 has no semantic voxel.
MESH_VERTICES = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1], [2, 0, 2]], np.float32)
MESH_FACES = np.array([[0, 1, 2], [1, 3, 2], [1, 4, 3]], np.int32)
LOG4 = float(np.log(4))


def _mesh_view_map(*, mesh_gt=None, confidence=None, gt_labels=None):
  mesh = mesh_lib.Mesh(
      vertices=MESH_VERTICES, faces=MESH_FACES,
      normals=np.tile(np.array([[0, 0, 1]], np.float32), (5, 1)),
      labels=np.array([0, 2, -1, 2, 1], np.int32),
      confidence=np.array([0.25, 0.625, 0.0, 1.0, 0.5], np.float32),
      entropy=np.array([0.0, LOG4 / 2, LOG4, LOG4, 2 * LOG4], np.float32),
      face_labels=np.array([0, 2, 1], np.int32))
  return dataclasses.replace(
      _view_map([0, 1], confidence=confidence, gt_labels=gt_labels), mesh=mesh,
      mesh_gt_labels=None if mesh_gt is None else np.asarray(mesh_gt, np.int32))


def test_what_is_shown_and_which_colour_modes():
  plain, meshed = _view_map([0, 1]), _mesh_view_map()
  for show in sd.SHOW_CHOICES:   # a map without a mesh always shows its voxels
    assert sd.shown_layers(plain, show) == (False, True)
  assert sd.shown_layers(meshed, "mesh") == (True, False)
  assert sd.shown_layers(meshed, "voxels") == (False, True)
  assert sd.shown_layers(meshed, "mesh + voxels") == (True, True)
  with pytest.raises(ValueError, match="show must be one of"):
    sd.shown_layers(meshed, "surface")
  assert sd.mesh_color_modes(plain) == ()
  assert sd.mesh_color_modes(meshed) == ("class", "entropy", "confidence")   # no GT
  assert sd.mesh_color_modes(_mesh_view_map(mesh_gt=[0] * 5)) == (
      "class", "entropy", "confidence", "correct")
  # No ᾱ and no GT on the voxels: the mesh has a max posterior, the voxels hit counts.
  assert sd.mode_titles(meshed, "mesh") == {"class": "class", "entropy": "entropy",
                                            "confidence": "confidence (max posterior)"}
  assert sd.mode_titles(meshed, "voxels") == {"class": "class", "entropy": "entropy",
                                              "hits": "hit count"}
  assert sd.mode_titles(meshed, "mesh + voxels") == {"class": "class", "entropy": "entropy"}
  full = _mesh_view_map(mesh_gt=[0] * 5, confidence=[1.0, 2.0], gt_labels=[0, 0])
  assert sd.mode_titles(full, "mesh + voxels") == {
      "class": "class", "entropy": "entropy",
      "confidence": "confidence (mesh: max posterior, voxels: ᾱ)",
      "correct": "right / wrong vs GT"}
  assert sd.mode_titles(full, "voxels") == sd.COLOR_MODES
  assert sd.mode_titles(plain, "mesh") == {m: sd.COLOR_MODES[m] for m in sd.color_modes(plain)}


def test_mesh_scalars_use_fixed_scales():
  m = _mesh_view_map()
  t, lo, hi, unit = sd.mesh_scalar(m, "entropy")   # [0, log K] nats, as the voxels
  np.testing.assert_allclose(t, [0.0, 0.5, 1.0, 1.0, 1.0], atol=1e-6)
  assert (lo, unit) == (0.0, "nats") and hi == pytest.approx(LOG4)
  t, lo, hi, unit = sd.mesh_scalar(m, "confidence")   # max posterior over [1/K, 1]
  np.testing.assert_allclose(t, [0.0, 0.5, 0.0, 1.0, 1 / 3], atol=1e-6)
  assert (lo, hi, unit) == (0.25, 1.0, "")
  with pytest.raises(ValueError, match="mesh colour mode"):
    sd.mesh_scalar(m, "hits")   # a count per voxel, not on the surface
  with pytest.raises(ValueError, match="no mesh"):
    sd.mesh_scalar(_view_map([0]), "entropy")


def test_mesh_colours_per_mode():
  palette = np.array([[1, 2, 3], [10, 20, 30], [200, 0, 0], [0, 200, 0]], np.uint8)
  grey = sd.NO_VOXEL_COLOR
  m = _mesh_view_map(mesh_gt=[0, 1, -1, 2, -1])
  np.testing.assert_array_equal(sd.mesh_colors(m, "class", palette),
                                [[1, 2, 3], [200, 0, 0], grey, [200, 0, 0], [10, 20, 30]])
  v0, v_half, v1 = _viridis([0.0, 0.5, 1.0])
  np.testing.assert_allclose(sd.mesh_colors(m, "entropy", None),
                             [v0, v_half, grey, v1, v1], atol=1)
  np.testing.assert_allclose(sd.mesh_colors(m, "confidence", None),
                             [v0, v_half, grey, v1, _viridis([1 / 3])[0]], atol=1)
  np.testing.assert_array_equal(
      sd.mesh_colors(m, "correct", None),
      [sd.RIGHT_COLOR, sd.WRONG_COLOR, sd.UNSCORED_COLOR, sd.RIGHT_COLOR, sd.UNSCORED_COLOR])
  assert sd.mesh_legend(m, "correct", None)[1:] == [
      ("right (2, accuracy 66.7 %)", sd.RIGHT_COLOR), ("wrong (1)", sd.WRONG_COLOR),
      ("not in GT (2)", sd.UNSCORED_COLOR)]
  assert sd.mesh_legend(m, "class", palette) == [
      ("mesh: vertices per class", None), ("wall (1)", (1, 2, 3)), ("chair (1)", (10, 20, 30)),
      ("table (2)", (200, 0, 0)), ("plant (0)", (0, 200, 0)),
      ("no semantic voxel (1)", grey)]
  with pytest.raises(ValueError, match="palette"):
    sd.mesh_colors(m, "class", palette[:3])
  with pytest.raises(ValueError, match="no GT"):
    sd.mesh_colors(_mesh_view_map(), "correct", None)
  assert "mesh: confidence" in sd.legend_html(sd.mesh_legend(m, "confidence", None))


def test_mesh_faces_by_class_and_height_and_their_part():
  m = _mesh_view_map()   # face classes 0, 2, 1; centroid heights 0, 1/3, 1
  np.testing.assert_array_equal(sd.mesh_face_mask(m), [1, 1, 1])
  np.testing.assert_array_equal(sd.mesh_face_mask(m, hidden_classes=[2]), [1, 0, 1])
  np.testing.assert_array_equal(sd.mesh_face_mask(m, max_height=0.5), [1, 1, 0])
  np.testing.assert_array_equal(sd.mesh_face_mask(m, hidden_classes={0}, max_height=0.5),
                                [0, 1, 0])
  np.testing.assert_array_equal(sd.mesh_face_mask(m, max_height=0.5, up_axis=0), [1, 0, 0])
  with pytest.raises(ValueError, match="hidden classes"):
    sd.mesh_face_mask(m, hidden_classes=[4])
  # The part keeps only the vertices its faces use, renumbered in order: 1, 2, 3, 4 → 0 … 3.
  colors = np.arange(15, dtype=np.uint8).reshape(5, 3)
  vertices, faces, part_colors, normals = sd.mesh_part(m, np.array([False, True, True]), colors)
  np.testing.assert_array_equal(vertices, MESH_VERTICES[1:])
  np.testing.assert_array_equal(faces, [[0, 2, 1], [0, 3, 2]])
  np.testing.assert_array_equal(vertices[faces], MESH_VERTICES[MESH_FACES[1:]])
  np.testing.assert_array_equal(part_colors, colors[1:])
  assert faces.dtype == np.int32 and normals.shape == (4, 3)
  empty = sd.mesh_part(m, np.zeros(3, bool), colors)
  assert [len(a) for a in empty] == [0, 0, 0, 0]
  # The mesh counts in the height slider's range and in the start view.
  assert sd.height_range([m]) == (0.0, 2.0)
  np.testing.assert_allclose(sd.initial_camera([m])[1], [1.0, 0.5, 1.0])


def test_mesh_glb_round_trips_with_a_rough_material():
  import json
  import struct
  trimesh = pytest.importorskip("trimesh")
  colors = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [128, 128, 128], [10, 20, 30]],
                    np.uint8)
  normals = np.tile(np.array([[0, 0, 1]], np.float32), (5, 1))
  glb = sd.mesh_glb(MESH_VERTICES, MESH_FACES, colors, normals)
  assert glb[:4] == b"glTF" and struct.unpack_from("<I", glb, 8)[0] == len(glb)
  scene = trimesh.load(io_lib.BytesIO(glb), file_type="glb", process=False)
  (mesh,) = scene.geometry.values()
  np.testing.assert_allclose(mesh.vertices, MESH_VERTICES)
  np.testing.assert_array_equal(mesh.faces, MESH_FACES)
  np.testing.assert_allclose(mesh.vertex_normals, normals, atol=1e-6)
  # The sRGB colours as they are (the page takes them for sRGB, as the cubes' colours).
  np.testing.assert_array_equal(mesh.visual.vertex_attributes["color"],
                                np.concatenate([colors, np.full((5, 1), 255)], axis=1))
  material = mesh.visual.material
  assert material.metallicFactor == 0.0 and material.roughnessFactor == 1.0
  json_length = struct.unpack_from("<I", glb, 12)[0]
  assert json_length % 4 == 0
  doc = json.loads(glb[20:20 + json_length])
  assert [p["material"] for p in doc["meshes"][0]["primitives"]] == [0]
  assert doc["materials"][0]["doubleSided"] is False


def test_vertex_gt_labels_by_brute_force():
  rng = np.random.default_rng(3)
  voxel = 0.1
  coords = np.unique(rng.integers(-5, 5, (300, 3)), axis=0).astype(np.int32)
  gt = rng.integers(-1, 4, len(coords)).astype(np.int32)
  points = rng.uniform(-0.5, 0.5, (400, 3)).astype(np.float32)
  points[:20] = np.round(points[:20] / voxel) * voxel   # on voxel faces
  points[20] = np.nan
  points[21] = [np.inf, 0, 0]
  points[22] = [1e12, 0, 0]   # beyond the key range
  table = {tuple(c): l for c, l in zip(coords.tolist(), gt.tolist())}
  keys = np.floor(points / np.float32(voxel))
  expected = [table.get(tuple(int(x) for x in k), -1) if np.all(np.abs(k) < 1e6) else -1
              for k in keys]
  got = sd.vertex_gt_labels(points, voxel, coords, gt)
  np.testing.assert_array_equal(got, expected)
  assert got.dtype == np.int32 and np.sum(got >= 0) > 40
  assert sd.vertex_gt_labels(points[:0], voxel, coords, gt).shape == (0,)
  np.testing.assert_array_equal(sd.vertex_gt_labels(points, voxel, coords[:0], gt[:0]), -1)


# The mesh of a saved map -------------------------------------------------------------------


def test_a_run_map_shows_its_mesh_with_gt_per_vertex(run_output):
  _, out = run_output
  (m,) = sd.load_maps([str(out)])
  state, _, _ = io.load_map(m.path)
  assert state.geometry is not None   # `jaxfusion run` keeps a geometry layer
  ref = jf.extract_mesh(state)
  assert m.mesh.num_faces == ref.num_faces > 0
  np.testing.assert_array_equal(m.mesh.vertices, ref.vertices)
  np.testing.assert_array_equal(m.mesh.labels, ref.labels)
  # Each vertex's GT: the GT label of the voxel floor(p / voxel) it lies in, by a dictionary
  # of the GT file beside the map (−1 for vertices without a label).
  gt = np.load(os.path.splitext(m.path)[0] + "_gt.npz")
  table = {tuple(c): int(l) for c, l in zip(gt["coords"].tolist(), gt["labels"].tolist())}
  keys = np.floor(m.mesh.vertices / np.float32(m.voxel_size)).astype(int)
  expected = [table.get(tuple(key), -1) if label >= 0 else -1
              for key, label in zip(keys.tolist(), m.mesh.labels.tolist())]
  np.testing.assert_array_equal(m.mesh_gt_labels, expected)
  scored = m.mesh_gt_labels >= 0
  assert np.all(m.mesh.labels[scored] >= 0) and scored.sum() > 1000
  # Predictions are the GT, softened: the mesh's vertices are mostly right.
  assert np.mean(m.mesh.labels[scored] == m.mesh_gt_labels[scored]) > 0.8
  assert sd.mesh_color_modes(m) == sd.MESH_COLOR_MODES


def test_maps_without_a_geometry_layer_or_faces_have_no_mesh(tmp_path, run_folder):
  root, _, _ = run_folder
  for m in sd.load_maps([str(root)]):
    assert m.mesh is None and m.mesh_gt_labels is None
    assert sd.mesh_color_modes(m) == ()
  rule = jf.rules.by_name("bayes")
  state = jf.init_map(capacity=256, num_classes=len(NAMES), voxel_size=0.25, rule=rule,
                      geometry=jf.TSDFConfig(capacity=2**4))   # nothing integrated: no face
  io.save_map(str(tmp_path / "empty.npz"), state, rule, class_names=NAMES)
  (m,) = sd.load_maps([str(tmp_path / "empty.npz")])
  assert m.mesh is None


# A mesh made later, and the preview meanwhile ----------------------------------------------


def test_a_mesh_left_for_later_is_the_one_load_makes(run_output):
  _, out = run_output
  (now,) = sd.load_maps([str(out)])
  lines = []
  (later,) = sd.load_maps([str(out)], mesh=False, progress=lines.append)
  assert lines == [f"loading {now.path} (1 of 1) …"]
  assert later.mesh is None and later.mesh_pending and not now.mesh_pending
  # Until the mesh is there the map offers the modes its mesh will have (GT is beside it).
  assert sd.mesh_color_modes(later) == sd.MESH_COLOR_MODES
  assert sd.shown_layers(later, "mesh") == (True, False)
  np.testing.assert_array_equal(later.labels, now.labels)
  made = sd.prepare_mesh(later, progress=lines.append)
  assert not made.mesh_pending and made.mesh_source is None
  for got, want in zip(made.mesh, now.mesh):
    np.testing.assert_array_equal(got, want)
  np.testing.assert_array_equal(made.mesh_gt_labels, now.mesh_gt_labels)
  faces, vertices = now.mesh.num_faces, now.mesh.num_vertices
  blocks = int(later.mesh_source.state.geometry.num_blocks)
  assert lines[1:] == [
      f"marching cubes on {blocks} blocks of the geometry layer …",
      f"labelling {vertices} vertices and {faces} faces from the semantic layer …",
      f"GT labels of {vertices} vertices …"]
  assert sd.prepare_mesh(made) is made   # nothing pending: nothing to do


def test_a_map_without_geometry_or_faces_has_no_mesh_pending(tmp_path, run_folder):
  root, _, _ = run_folder
  for m in sd.load_maps([str(root)], mesh=False):
    assert not m.mesh_pending and sd.prepare_mesh(m) is m
    assert sd.shown_layers(m, "mesh") == (False, True)
  rule = jf.rules.by_name("bayes")
  state = jf.init_map(capacity=256, num_classes=len(NAMES), voxel_size=0.25, rule=rule,
                      geometry=jf.TSDFConfig(capacity=2**4))   # nothing integrated: no face
  io.save_map(str(tmp_path / "empty.npz"), state, rule, class_names=NAMES)
  m = sd.load_view_map(str(tmp_path / "empty.npz"), mesh=False)
  assert m.mesh_pending
  lines = []
  made = sd.prepare_mesh(m, progress=lines.append)
  assert made.mesh is None and not made.mesh_pending and len(lines) == 1   # no face to label
  assert sd.shown_layers(made, "mesh") == (False, True)


def test_coarse_voxels_keep_one_voxel_of_each_coarse_cell():
  rng = np.random.default_rng(0)
  size = 0.1
  keys = rng.permutation(np.unique(rng.integers(-20, 20, (3000, 3)), axis=0))
  n = len(keys)
  m = dataclasses.replace(
      _view_map(rng.integers(0, len(NAMES), n), centers=(keys + 0.5) * size,
                hits=rng.integers(1, 100, n), entropy=rng.uniform(0, 1, n),
                confidence=rng.uniform(1, 9, n), gt_labels=rng.integers(-1, len(NAMES), n)),
      voxel_size=size)
  assert sd.coarse_voxels(m, max_voxels=n) is m   # small enough: as it is
  c = sd.coarse_voxels(m, max_voxels=n // 10)
  assert 0 < len(c) <= n // 10
  f = int(round(c.voxel_size / size))
  assert f >= 2 and f & (f - 1) == 0 and np.isclose(c.voxel_size, f * size)
  # Cells of half the size would not have fitted: they are the smallest that do.
  assert len(np.unique(keys // (f // 2), axis=0)) > n // 10
  # Each cell holds its voxel nearest the cell's centre (the first of equals), with all its
  # values, drawn at the centre: by a dictionary of the cells.
  cells = {}
  for i, key in enumerate(keys.tolist()):
    cells.setdefault(tuple(k // f for k in key), []).append(i)
  assert len(c) == len(cells)
  palette = sd.class_palette(NAMES)
  for j, centre in enumerate(c.centers):
    cell = tuple(int(x) for x in np.floor(centre / c.voxel_size))
    np.testing.assert_allclose(centre, (np.array(cell) + 0.5) * c.voxel_size, atol=1e-5)
    members = cells.pop(cell)
    twice_offset = [sum((2 * (keys[i][a] - cell[a] * f) - (f - 1)) ** 2 for a in range(3))
                    for i in members]
    nearest = members[int(np.argmin(twice_offset))]
    for field in ("labels", "hits", "entropy", "confidence", "gt_labels"):
      assert getattr(c, field)[j] == getattr(m, field)[nearest], field
    np.testing.assert_array_equal(sd.voxel_colors(c, "class", palette)[j],
                                  palette[m.labels[nearest]])
  assert not cells   # every cell with a voxel has its cube
  # So the cubes cover the voxels' bounds and reach less than a cell past them.
  half = c.voxel_size / 2
  lo, hi = m.centers.min(0) - size / 2, m.centers.max(0) + size / 2
  np.testing.assert_array_less(c.centers.min(0) - half, lo + 1e-6)
  np.testing.assert_array_less(hi - 1e-6, c.centers.max(0) + half)
  np.testing.assert_array_less(lo - c.voxel_size, c.centers.min(0) - half)
  np.testing.assert_array_less(c.centers.max(0) + half, hi + c.voxel_size)
  with pytest.raises(ValueError, match="max_voxels"):
    sd.coarse_voxels(m, max_voxels=0)
