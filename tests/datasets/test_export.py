"""Writing embedded sequences in ScanNet's and TUM's layouts, and reading them back with the
real-data readers; the labelled GT mesh and its PLY file; `jaxfusion save --format`."""

import os

import numpy as np
import pytest

from jaxfusion.camera import Camera
from jaxfusion.datasets import (classes, export, files, plyfile, primitives, scannet, synthetic,
                                tum)
from jaxfusion.datasets.classes import CLASS_NAMES
from jaxfusion.datasets.primitives import BOX, CYLINDER, SPHERE


@pytest.fixture(scope="module")
def source():
  return synthetic.make_sequence("office", 0, num_frames=3, height=24, width=32, seed=1)


def _rotation(axis, angle):
  axis = np.asarray(axis, np.float64) / np.linalg.norm(axis)
  K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
  return np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K


# --- ScanNet ------------------------------------------------------------------------------------

def test_scannet_round_trip_through_load_scannet(source, tmp_path):
  path = str(tmp_path / "scene0001_00")
  assert export.save_scannet(source, path, color_size=(48, 64)) == path
  for sub, ext in (("color", "jpg"), ("depth", "png"), ("pose", "txt"), ("label-filt", "png")):
    assert sorted(os.listdir(os.path.join(path, sub))) == [f"{i}.{ext}" for i in range(3)]
  assert sorted(os.listdir(os.path.join(path, "intrinsic"))) == sorted(
      ["intrinsic_depth.txt", "intrinsic_color.txt", "extrinsic_depth.txt",
       "extrinsic_color.txt"])
  seq = scannet.load_scannet(path, label_space="embedded")
  assert len(seq) == 3 and seq.info["num_skipped"] == 0 and seq.name == "scene0001_00"
  assert seq.class_names == CLASS_NAMES
  assert tuple(seq.camera) == tuple(source.camera)
  np.testing.assert_allclose(seq.depth, source.depth, rtol=0, atol=0.0005)
  assert np.array_equal(seq.depth == 0, source.depth == 0)
  np.testing.assert_allclose(seq.T_world_cam, source.T_world_cam, rtol=0, atol=1e-6)
  # Upsampled ×2 by pixel centre and read back by the reader's nearest pixel: with an integer
  # factor every label comes back (see the next test for other sizes).
  assert np.array_equal(seq.labels, source.labels)
  # Colour: bilinear up, JPEG, area down: close to the original on average.
  assert np.mean(np.abs(seq.rgb.astype(int) - source.rgb.astype(int))) < 6


def test_scannet_files_are_laid_out_as_sensreader_and_scannet_write_them(source, tmp_path):
  import cv2
  path = str(tmp_path / "scene")
  export.save_scannet(source, path, color_size=(48, 64))
  assert cv2.imread(os.path.join(path, "color", "0.jpg")).shape == (48, 64, 3)
  depth = cv2.imread(os.path.join(path, "depth", "0.png"), cv2.IMREAD_UNCHANGED)
  assert depth.dtype == np.uint16 and depth.shape == (24, 32)
  assert np.array_equal(depth, np.round(source.depth[0] * 1000).astype(np.uint16))
  label = cv2.imread(os.path.join(path, "label-filt", "0.png"), cv2.IMREAD_UNCHANGED)
  assert label.dtype == np.uint16 and label.shape == (48, 64)
  assert set(np.unique(label)) <= set(classes.EMBEDDED_TO_NYU40.tolist()) | {0}
  pose = open(os.path.join(path, "pose", "0.txt")).read().splitlines()
  assert len(pose) == 4 and all(len(row.split(" ")) == 4 for row in pose)
  np.testing.assert_array_equal(np.loadtxt(os.path.join(path, "pose", "0.txt")).astype(np.float32),
                                source.T_world_cam[0])
  K_color = np.loadtxt(os.path.join(path, "intrinsic", "intrinsic_color.txt"))
  c = source.camera
  np.testing.assert_allclose(K_color, [[2 * c.fx, 0, 2 * c.cx + 0.5, 0],
                                       [0, 2 * c.fy, 2 * c.cy + 0.5, 0], [0, 0, 1, 0],
                                       [0, 0, 0, 1]], atol=1e-12)
  for name in ("extrinsic_depth.txt", "extrinsic_color.txt"):
    np.testing.assert_array_equal(np.loadtxt(os.path.join(path, "intrinsic", name)), np.eye(4))


def _edges(labels):
  """Pixels with a differently labelled pixel among their 8 neighbours."""
  edge = np.zeros(labels.shape, bool)
  for dy in (-1, 0, 1):
    for dx in (-1, 0, 1):
      edge |= labels != np.roll(labels, (dy, dx), axis=(-2, -1))
  return edge


def test_scannet_labels_at_scannets_own_sizes(source, tmp_path):
  # ScanNet's colour is 2.025 × its depth width and 2.017 × its height: not integers. The label
  # images are upsampled by pixel centre and `load_scannet` reads them back by pixel centre
  # (cv2.INTER_NEAREST_EXACT): each depth pixel's centre falls inside a colour pixel whose
  # centre maps back into the same depth pixel, so the labels come back exactly.
  big = lambda x: np.repeat(np.repeat(x[:1], 20, axis=1), 20, axis=2)   # 24×32 → 480×640
  seq = source.__class__(name="s", class_names=CLASS_NAMES, camera=source.camera,
                         rgb=big(source.rgb), depth=big(source.depth),
                         T_world_cam=source.T_world_cam[:1], labels=big(source.labels))
  path = str(tmp_path / "scene")
  export.save_scannet(seq, path)   # the default 968×1296 colour
  labels = scannet.load_scannet(path, label_space="embedded").labels
  np.testing.assert_array_equal(labels, seq.labels)
  # At a tiny size with a ratio just above 2 the same holds except, at most, next to edges.
  export.save_scannet(source, path, color_size=(49, 65), overwrite=True)
  same = scannet.load_scannet(path, label_space="embedded").labels == source.labels
  assert same.mean() >= 0.9 and np.all(same | _edges(source.labels))


def test_scannet_labels_of_other_label_spaces_and_ignored_pixels(source, tmp_path):
  assert np.array_equal(export.nyu40_ids(CLASS_NAMES), classes.EMBEDDED_TO_NYU40)
  names, lut = classes.label_space("scannet12")
  assert np.array_equal(lut[export.nyu40_ids(names)], np.arange(len(names)))
  with pytest.raises(ValueError, match="label space"):
    export.nyu40_ids(("cat", "dog"))
  labels = source.labels.copy()
  labels[:, :4] = classes.IGNORE_LABEL
  seq = source.__class__(name="s", class_names=CLASS_NAMES, camera=source.camera,
                         rgb=source.rgb, depth=source.depth, T_world_cam=source.T_world_cam,
                         labels=labels)
  path = str(tmp_path / "scene")
  export.save_scannet(seq, path, color_size=(48, 64))
  assert np.array_equal(scannet.load_scannet(path, label_space="embedded").labels, labels)


def test_scannet_target_folder_rules(source, tmp_path):
  foreign = tmp_path / "foreign"
  foreign.mkdir()
  (foreign / "notes.txt").write_text("mine")
  with pytest.raises(ValueError, match="not empty and not a scannet export"):
    export.save_scannet(source, str(foreign), color_size=(48, 64))
  assert os.listdir(foreign) == ["notes.txt"]
  export.save_scannet(source, str(foreign), color_size=(48, 64), overwrite=True)
  assert (foreign / "notes.txt").exists() and (foreign / "intrinsic").is_dir()
  # Re-exporting into an earlier export replaces it, leaving no stale frame behind.
  path = str(tmp_path / "scene")
  export.save_scannet(source, path, color_size=(48, 64))
  export.save_scannet(source.subset([0, 1]), path, color_size=(48, 64))
  assert len(scannet.load_scannet(path)) == 2
  assert sorted(os.listdir(os.path.join(path, "color"))) == ["0.jpg", "1.jpg"]
  a_file = tmp_path / "file"
  a_file.write_text("x")
  with pytest.raises(ValueError, match="is a file"):
    export.save_scannet(source, str(a_file))
  with pytest.raises(ValueError, match="aspect ratio"):
    export.save_scannet(source, str(tmp_path / "wide"), color_size=(24, 64))


# --- TUM ----------------------------------------------------------------------------------------

def test_quaternions_of_all_rotations_including_half_turns():
  rng = np.random.default_rng(0)
  axes = rng.normal(size=(200, 3))
  angles = np.concatenate([rng.uniform(0, np.pi, 100), np.pi - 10.0 ** -rng.uniform(1, 9, 60),
                           np.full(20, np.pi), np.zeros(20)])
  Rs = np.stack([_rotation(a, t) for a, t in zip(axes, angles)])
  Rs = np.concatenate([Rs, np.diag([1.0, -1, -1])[None], np.diag([-1.0, 1, -1])[None],
                       np.diag([-1.0, -1, 1])[None]])
  q = export.rotation_to_quaternion(Rs)
  assert q.shape == (len(Rs), 4) and np.all(q[:, 3] >= 0)
  np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-12)
  for R, qi in zip(Rs, q):
    np.testing.assert_allclose(tum.quat_to_pose(np.zeros(3), qi)[:3, :3], R, atol=1e-12)
  # float32 poses, slightly off orthonormal, still give unit quaternions of the rotation.
  R32 = Rs.astype(np.float32)
  for R, qi in zip(R32, export.rotation_to_quaternion(R32)):
    np.testing.assert_allclose(tum.quat_to_pose(np.zeros(3), qi)[:3, :3], R, atol=1e-6)
  with pytest.raises(ValueError, match="reflection"):
    export.rotation_to_quaternion(np.diag([1.0, 1, -1]))


def test_tum_round_trip_through_load_tum(source, tmp_path):
  path = str(tmp_path / "tum_seq")
  assert export.save_tum(source, path) == path
  assert sorted(os.listdir(path)) == ["associations.txt", "calibration.txt", "depth",
                                      "depth.txt", "groundtruth.txt", "rgb", "rgb.txt"]
  seq = tum.load_tum(path)
  assert len(seq) == 3 and seq.info["num_skipped"] == 0
  assert tuple(seq.camera) == tuple(source.camera)
  assert np.array_equal(seq.rgb, source.rgb)   # PNG: lossless
  np.testing.assert_allclose(seq.depth, source.depth, rtol=0, atol=0.5 / 5000 + 1e-7)
  np.testing.assert_allclose(seq.T_world_cam, source.T_world_cam, rtol=0, atol=1e-5)
  # The stamps differ by stream, the association pairs each depth image with its own frame.
  stamps = np.array(seq.info["timestamps"])
  np.testing.assert_allclose(stamps, 1305031102.0 + np.arange(3) / 30 + 0.005, atol=1e-6)
  rgb = tum.read_list(os.path.join(path, "rgb.txt"), 2)
  gt = tum.read_list(os.path.join(path, "groundtruth.txt"), 8)
  assert all(0 < abs(d[0] - r[0]) < 0.02 and 0 < abs(d[0] - g[0]) < 0.02
             for d, r, g in zip(tum.read_list(os.path.join(path, "depth.txt"), 2), rgb, gt))
  for line in open(os.path.join(path, "associations.txt")).read().splitlines():
    t_rgb, rgb_file, t_depth, depth_file = line.split()
    assert rgb_file == f"rgb/{t_rgb}.png" and depth_file == f"depth/{t_depth}.png"
    assert os.path.isfile(os.path.join(path, rgb_file))
  headers = [open(os.path.join(path, n)).readline() for n in ("rgb.txt", "groundtruth.txt")]
  assert headers == ["# color images\n", "# ground truth trajectory\n"]
  # Without calibration.txt a reader needs the camera passed in.
  os.remove(os.path.join(path, "calibration.txt"))
  assert tuple(tum.load_tum(path).camera) != tuple(source.camera)
  assert tuple(tum.load_tum(path, camera=source.camera).camera) == tuple(source.camera)


def test_tum_rewrite_bad_rate_and_bad_calibration(source, tmp_path):
  path = str(tmp_path / "tum_seq")
  export.save_tum(source, path)
  export.save_tum(source.subset([0]), path, rate_hz=100.0)   # an earlier export: replaced
  assert len(os.listdir(os.path.join(path, "rgb"))) == 1 and len(tum.load_tum(path)) == 1
  with pytest.raises(ValueError, match="rate_hz"):
    export.save_tum(source, str(tmp_path / "other"), rate_hz=0.0)
  with open(os.path.join(path, "calibration.txt"), "w") as f:
    f.write("1 2 3\n")
  with pytest.raises(ValueError, match="calibration.txt"):
    tum.load_tum(path)


# --- The labelled mesh --------------------------------------------------------------------------

def _table(kinds, half_sizes, labels, centers=None, rotations=None):
  n = len(kinds)
  zeros = np.zeros((n, 3), np.float32)
  return primitives.Primitives(
      kind=np.asarray(kinds, np.int32),
      center=zeros if centers is None else np.asarray(centers, np.float32),
      rotation=np.tile(np.eye(3, dtype=np.float32), (n, 1, 1)) if rotations is None
      else np.asarray(rotations, np.float32),
      half_size=np.asarray(half_sizes, np.float32), label=np.asarray(labels, np.int32),
      instance=np.arange(1, n + 1, dtype=np.int32), color=zeros, color2=zeros,
      texture=np.zeros(n, np.int32), texture_scale=np.zeros(n, np.float32),
      emission=np.zeros(n, np.float32), gloss=np.zeros(n, np.float32))


def _signed_volume(vertices, faces):
  a, b, c = (vertices[faces[:, k]] for k in range(3))
  return np.sum(np.einsum("ij,ij->i", a, np.cross(b, c))) / 6


def test_mesh_of_known_primitives():
  R = _rotation([1, 2, 3], 0.7)
  box = _table([BOX], [[0.5, 0.25, 1.0]], [3], centers=[[1, 2, 3]], rotations=[R])
  mesh = export.primitives_mesh(box)
  assert mesh["vertices"].shape == (8, 3) and mesh["faces"].shape == (12, 3)
  assert np.all(mesh["labels"] == 3)
  assert _signed_volume(mesh["vertices"], mesh["faces"]) == pytest.approx(8 * 0.5 * 0.25 * 1.0)
  np.testing.assert_allclose(primitives.surface_distance(box, mesh["vertices"]), 0, atol=1e-6)
  # Split into a grid: 0.5 m edges give 2 × 1 × 4 cells per axis, 2·(2·1 + 1·4 + 4·2) cells.
  fine = export.primitives_mesh(box, spacing=0.5)
  assert fine["faces"].shape == (2 * 2 * (2 + 4 + 8), 3)
  assert fine["vertices"].shape == (3 * 2 * 5 - 1 * 0 * 3, 3)   # the lattice less its inside
  assert _signed_volume(fine["vertices"], fine["faces"]) == pytest.approx(1.0)
  cyl = _table([CYLINDER, SPHERE], [[0.3, 0.3, 0.5], [0.2, 0.2, 0.2]], [1, 2],
               centers=[[0, 0, 0], [2, 0, 0]])
  mesh = export.primitives_mesh(cyl, segments=16)
  n_cyl = int(np.sum(mesh["primitive"] == 0))
  assert n_cyl == 2 * 16 + 2 and len(mesh["vertices"]) == n_cyl + 2 + 7 * 16
  assert np.all(mesh["labels"] == np.where(mesh["primitive"] == 0, 1, 2))
  np.testing.assert_allclose(primitives.surface_distance(cyl, mesh["vertices"]), 0, atol=1e-6)
  assert _signed_volume(mesh["vertices"], mesh["faces"]) > 0
  with pytest.raises(ValueError, match="bounds"):
    export.primitives_mesh(_table([primitives.PLANE], [[1, 1, 1]], [0]))


def test_embedded_mesh_lies_on_the_scene_surface_in_the_world_frame():
  mesh = export.embedded_labelled_mesh("office", 1, 1.0, spacing=None)
  world = synthetic.make_scene("office", seed=1, domain="test", shift=1.0)
  T = synthetic.placement("office", 1)
  room = (mesh["vertices"] - T[:3, 3]) @ T[:3, :3]   # back into the room's frame
  np.testing.assert_allclose(primitives.surface_distance(world.primitives, room), 0, atol=1e-5)
  lx, ly, h = world.layout.room
  assert np.all(room >= -1e-6) and np.all(room <= np.array([lx, ly, h]) + 1e-6)
  assert set(np.unique(mesh["labels"])) <= set(classes.EMBEDDED_TO_NYU40.tolist())
  assert classes.EMBEDDED_TO_NYU40[classes.CHAIR] in mesh["labels"]
  assert np.all(mesh["faces"] < len(mesh["vertices"]))
  dense = export.embedded_labelled_mesh("office", 1, 1.0, spacing=0.2)
  assert len(dense["vertices"]) > 2 * len(mesh["vertices"])
  edges = dense["vertices"][dense["faces"]] - np.roll(dense["vertices"][dense["faces"]], 1, 1)
  assert np.linalg.norm(edges, axis=-1).max() < 0.2 * np.sqrt(2) + 1e-6


def test_labelled_mesh_ply_reads_back_exactly(tmp_path):
  rng = np.random.default_rng(0)
  mesh = {"vertices": rng.normal(size=(50, 3)).astype(np.float32),
          "faces": rng.integers(0, 50, size=(70, 3)).astype(np.int32),
          "labels": rng.integers(0, 41, size=50).astype(np.int32)}
  path = str(tmp_path / "scene_vh_clean_2.labels.ply")
  plyfile.write_labelled_mesh(path, mesh)
  with open(path, "rb") as f:
    header = f.read().split(b"end_header")[0].decode()
  assert [line for line in header.splitlines() if line.startswith(("element", "property"))] == [
      "element vertex 50", "property float x", "property float y", "property float z",
      "property uchar red", "property uchar green", "property uchar blue", "property uchar alpha",
      "property ushort label", "element face 70", "property list uchar int vertex_indices"]
  back = plyfile.read_labelled_mesh(path)
  for key in ("vertices", "faces", "labels"):
    assert np.array_equal(back[key], mesh[key]) and back[key].dtype == mesh[key].dtype
  ply = plyfile.read_ply(path)
  assert np.array_equal(np.stack([ply["vertex"][c] for c in ("red", "green", "blue", "alpha")],
                                 -1), plyfile.label_colors(mesh["labels"]))
  # ASCII, with a quad (split into two triangles) and an extra property.
  ascii_path = tmp_path / "ascii.ply"
  ascii_path.write_text(
      "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
      "property float z\nproperty int label\nproperty float quality\nelement face 2\n"
      "property list uchar int vertex_indices\nend_header\n"
      "0 0 0 5 1\n1 0 0 5 1\n1 1 0 7 1\n0 1 0 7 1\n3 0 1 2\n4 0 1 2 3\n")
  back = plyfile.read_labelled_mesh(str(ascii_path))
  assert back["labels"].tolist() == [5, 5, 7, 7]
  assert back["faces"].tolist() == [[0, 1, 2], [0, 1, 2], [0, 2, 3]]
  # One clear line for a mesh without labels, and for a cut-off file.
  plain = tmp_path / "plain.ply"
  plain.write_text("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                   "property float z\nend_header\n0 0 0\n")
  with pytest.raises(ValueError, match="no 'label' vertex property") as info:
    plyfile.read_labelled_mesh(str(plain))
  assert "\n" not in str(info.value) and str(plain) in str(info.value)
  data = open(path, "rb").read()
  (tmp_path / "cut.ply").write_bytes(data[:-10])
  with pytest.raises(ValueError, match="cut short"):
    plyfile.read_labelled_mesh(str(tmp_path / "cut.ply"))
  with pytest.raises(FileNotFoundError):
    plyfile.read_labelled_mesh(str(tmp_path / "missing.ply"))


def test_save_scannet_writes_the_labelled_mesh(source, tmp_path):
  mesh = export.embedded_labelled_mesh("office", 1, 1.0, spacing=None)
  path = str(tmp_path / "scene0002_00")
  export.save_scannet(source, path, color_size=(48, 64), labelled_mesh=mesh)
  back = plyfile.read_labelled_mesh(os.path.join(path, "scene0002_00_vh_clean_2.labels.ply"))
  np.testing.assert_array_equal(back["vertices"], mesh["vertices"].astype(np.float32))
  assert np.array_equal(back["faces"], mesh["faces"])
  assert np.array_equal(back["labels"], mesh["labels"])
  ply = plyfile.read_ply(os.path.join(path, "scene0002_00_vh_clean_2.labels.ply"))
  assert np.array_equal(np.stack([ply["vertex"][c] for c in ("red", "green", "blue")], -1),
                        mesh["colors"][:, :3])


# --- The command --------------------------------------------------------------------------------

def test_save_command_writes_scannet_and_tum_and_refuses_a_bad_folder(tmp_path, capsys):
  from jaxfusion.lab import cli
  out = str(tmp_path / "scene0003_00")
  small = ["--num-frames", "2", "--height", "24", "--width", "32"]
  assert cli.main(["save", "--format", "scannet", *small, "--out", out]) == 0
  printed = capsys.readouterr().out.splitlines()
  assert len(printed) == 1 and "ScanNet" in printed[0]
  seq = scannet.load_scannet(out, label_space="embedded")
  assert len(seq) == 2 and seq.depth.shape == (2, 24, 32) and seq.class_names == CLASS_NAMES
  assert files.read_rgb(os.path.join(out, "color", "0.jpg")).shape == (968, 1296, 3)
  small.append("--no-realism")   # the exact renderer: quicker, and enough for the layout
  mesh = plyfile.read_labelled_mesh(os.path.join(out, "scene0003_00_vh_clean_2.labels.ply"))
  assert len(mesh["vertices"]) > 1000
  tum_out = str(tmp_path / "tum")
  assert cli.main(["save", "--format", "tum", *small, "--out", tum_out]) == 0
  printed = capsys.readouterr().out.splitlines()
  assert len(printed) == 2 and printed[1].startswith("camera: fx=19.2")
  assert len(tum.load_tum(tum_out)) == 2
  (tmp_path / "busy").mkdir()
  (tmp_path / "busy" / "thesis.tex").write_text("x")
  assert cli.main(["save", "--format", "scannet", *small, "--out",
                   str(tmp_path / "busy")]) == 2
  err = capsys.readouterr().err.strip()
  assert len(err.splitlines()) == 1 and "not empty" in err and "--overwrite" in err
  assert cli.main(["save", "--format", "tum", *small, "--color-size", "48", "64", "--out",
                   str(tmp_path / "t2")]) == 2
  assert "--color-size" in capsys.readouterr().err


def test_save_command_default_sizes_by_format():
  from jaxfusion.lab import data
  assert data.SAVE_SIZES["scannet"] == (480, 640) and data.SAVE_SIZES["saved"] == (240, 320)
  assert export.SCANNET_COLOR_SIZE == (968, 1296)
  assert Camera(*export.resized_camera(Camera(100, 100, 319.5, 239.5), (480, 640),
                                         (968, 1296))) == pytest.approx(
      (202.5, 100 * 968 / 480, 647.5, 483.5))
