"""The viewer's pure parts: finding and loading maps, colours per mode, legend, filters, and the
`view` command's one-line errors. No browser and no viser needed."""

import os
import sys

import matplotlib
import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion.lab import cli
from jaxfusion import io
from jaxfusion.lab.viewer import scene_data as sd
from tests import engine_helpers as h

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


def test_maps_from_jaxfusion_run_carry_poses_and_gt(tmp_path, capsys):
  from jaxfusion import datasets, sources
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
  capsys.readouterr()
  (m,) = sd.load_maps([str(out)])
  assert m.sequence == seq.name and m.class_names == tuple(seq.class_names)
  np.testing.assert_array_equal(m.poses, seq.T_world_cam)
  assert m.camera == {"fx": seq.camera.fx, "fy": seq.camera.fy, "cx": seq.camera.cx,
                      "cy": seq.camera.cy, "height": 24, "width": 32}
  assert m.gt_labels is not None and np.mean(m.gt_labels >= 0) > 0.9
  assert "correct" in sd.color_modes(m)
