"""`jaxfusion gt`: the GT file it writes is what `jaxfusion eval` and `metrics.evaluate_map`
read; the labelled mesh of a ScanNet folder is found and used (and agrees with the label
images of the same scene); bad inputs are one line and exit 2."""

import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import datasets, io, metrics
from jaxfusion.datasets import classes, export, plyfile
from jaxfusion.lab import cli
from jaxfusion.lab import ground_truth as gt_command

EMBEDDED = ["--data", "office:0", "--frames", "2", "--height", "24", "--width", "32"]


@pytest.fixture(scope="module")
def office():
  return datasets.make_sequence("office", 0, num_frames=2, height=24, width=32, seed=0)


@pytest.fixture(scope="module")
def written(office, tmp_path_factory):
  path = str(tmp_path_factory.mktemp("gt") / "gt.npz")
  assert cli.main(["gt", *EMBEDDED, "--out", path]) == 0
  return path


def test_the_file_holds_the_gt_of_the_sequence(office, written, capsys):
  f = io.read_npz(written, what="GT file")
  assert set(f) == {"coords", "labels", "hits", "class_names", "source", "voxel_size"}
  assert f["coords"].dtype == f["labels"].dtype == f["hits"].dtype == np.int32
  assert f["coords"].shape == (len(f["labels"]), 3) and len(f["labels"]) > 100
  assert tuple(f["class_names"]) == classes.CLASS_NAMES and str(f["source"]) == "images"
  want = datasets.gt_voxel_labels(office, voxel_size=0.1)
  for k in ("coords", "labels", "hits"):
    np.testing.assert_array_equal(f[k], want[k])


def test_eval_and_evaluate_map_read_the_file(office, written, tmp_path, capsys):
  # A map of the GT labels themselves scores 100 %.
  rule = jf.rules.sum_labels()
  state = jf.init_map(capacity=2**13, num_classes=office.num_classes, rule=rule)
  for frame in office:
    probs = np.eye(office.num_classes, dtype=np.float32)[frame.labels]
    state = jf.fuse_frame(state, jf.Frame(frame.depth, frame.T_world_cam, probs),
                          office.camera, rule)
  map_path = str(tmp_path / "map.npz")
  io.save_map(map_path, state, rule, class_names=office.class_names)
  gt = io.read_npz(written, what="GT file")
  ev = metrics.evaluate_map(jf.read_map(state), gt, office.num_classes,
                            ignore_label=datasets.IGNORE_LABEL)
  assert ev["miou"] == 1.0 and ev["matched"] == len(gt["labels"])
  capsys.readouterr()
  assert cli.main(["eval", "--map", map_path, "--gt", written]) == 0
  assert "mIoU 100.0" in capsys.readouterr().out


def test_a_label_space_reads_the_embedded_classes_through_nyu40(written, tmp_path, capsys):
  path = str(tmp_path / "gt12.npz")
  assert cli.main(["gt", *EMBEDDED, "--label-space", "scannet12", "--out", path]) == 0
  line = capsys.readouterr().out.strip()
  assert line.startswith("GT: ") and "12 classes" in line and path in line
  f, own = io.read_npz(path, what="GT file"), io.read_npz(written, what="GT file")
  assert tuple(f["class_names"]) == classes.SCANNET_CLASS_NAMES
  names = classes.SCANNET_CLASS_NAMES
  # Walls (the embedded background) are no class of scannet12; the rest keep their voxels.
  assert set(f["labels"]) <= {names.index(n) for n in ("objects", "chair", "table", "sofa", "tv")}
  assert 0 < len(f["labels"]) < len(own["labels"])


CHAIR_QUAD = {"vertices": np.array([[0.01, 0.01, 0.05], [0.29, 0.01, 0.05], [0.29, 0.19, 0.05],
                                     [0.01, 0.19, 0.05]]),
              "faces": np.array([[0, 1, 2], [0, 2, 3]]), "labels": np.array([5, 5, 5, 5])}


def _scannet_folder_with_a_mesh(tmp_path, mesh=None):
  """A folder holding only `scene0000_00_vh_clean_2.labels.ply` (`mesh`, or not a PLY)."""
  folder = tmp_path / "scene0000_00"
  folder.mkdir()
  path = str(folder / "scene0000_00_vh_clean_2.labels.ply")
  if mesh is None:
    (folder / "scene0000_00_vh_clean_2.labels.ply").write_bytes(b"ply\n")
  else:
    plyfile.write_labelled_mesh(path, mesh)
  return str(folder)


def test_a_scannet_folder_with_its_labelled_mesh(tmp_path, capsys):
  folder = _scannet_folder_with_a_mesh(tmp_path, CHAIR_QUAD)      # NYU40 chair, 6 voxels
  assert gt_command.find_labelled_mesh(folder).endswith("scene0000_00_vh_clean_2.labels.ply")
  out = str(tmp_path / "gt.npz")
  for source in ("auto", "mesh"):
    assert cli.main(["gt", "--data", f"scannet:{folder}", "--source", source,
                     "--out", out]) == 0
    f = io.read_npz(out, what="GT file")
    assert str(f["source"]) == "mesh" and tuple(f["class_names"]) == classes.SCANNET_CLASS_NAMES
    np.testing.assert_array_equal(f["coords"], [[i, j, 0] for i in range(3) for j in range(2)])
    assert set(f["labels"]) == {classes.SCANNET_CLASS_NAMES.index("chair")}
  assert "from mesh" in capsys.readouterr().out
  assert cli.main(["gt", "--data", f"scannet:{folder}", "--label-space", "nyu40",
                   "--out", out]) == 0
  assert set(io.read_npz(out, what="GT file")["labels"]) == {4}   # chair, NYU40 id 5


def test_an_embedded_scene_in_scannet_layout_mesh_and_images_agree(office, tmp_path):
  # The embedded room written as ScanNet writes a scene: label images and the labelled mesh.
  folder = export.save_scannet(office, str(tmp_path / "scene0001_00"), color_size=(48, 64),
                               labelled_mesh=export.embedded_labelled_mesh("office", 0, 1.0,
                                                                           spacing=None))
  gts = {}
  for source in ("mesh", "images"):
    out = str(tmp_path / f"{source}.npz")
    assert cli.main(["gt", "--data", f"scannet:{folder}", "--label-space", "embedded",
                     "--voxel-size", "0.2", "--source", source, "--out", out]) == 0
    f = io.read_npz(out, what="GT file")
    gts[source] = {tuple(c): l for c, l in zip(f["coords"], f["labels"])}
  mesh, images = gts["mesh"], gts["images"]
  common = set(mesh) & set(images)
  assert len(common) > 0.8 * len(images)                 # the mesh covers what the frames saw
  assert np.mean([mesh[k] == images[k] for k in common]) > 0.9


def _unlabelled_saved(tmp_path):
  seq = datasets.RGBDSequence("plain", (), jf.Camera(4.0, 4.0, 3.5, 3.5),
                              np.zeros((1, 8, 8, 3), np.uint8), np.ones((1, 8, 8)),
                              np.eye(4)[None])
  return seq.save(str(tmp_path / "plain"))


@pytest.mark.parametrize("argv,message", [
    (["--data", "office:9"], "--data: "),
    (["--data", "office:0", "--label-space", "coco"], "unknown label space 'coco'"),
    (["--data", "office:0", "--source", "mesh"], "no *_vh_clean_2.labels.ply"),
    (["--data", "tum:/no/such/folder"], "no such folder"),
    (["--data", "office:0", "--voxel-size", "0"], "--voxel-size must be positive"),
    ("unlabelled", "no ground-truth labels"),
    ("scannet without frames", "not a ScanNet export"),
    ("corrupt mesh", "scene0000_00_vh_clean_2.labels.ply"),
])
def test_bad_inputs_are_one_line_and_exit_2(argv, message, tmp_path, capsys):
  if argv == "unlabelled":
    argv = ["--data", f"saved:{_unlabelled_saved(tmp_path)}"]
  elif argv == "scannet without frames":
    argv = ["--data", f"scannet:{_scannet_folder_with_a_mesh(tmp_path)}", "--source", "images"]
  elif argv == "corrupt mesh":
    argv = ["--data", f"scannet:{_scannet_folder_with_a_mesh(tmp_path)}"]
  assert cli.main(["gt", *argv, "--out", str(tmp_path / "gt.npz")]) == 2
  err = capsys.readouterr().err
  assert message in err and err.count("\n") == 1 and "Traceback" not in err
  assert not (tmp_path / "gt.npz").exists()
