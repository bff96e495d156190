"""ScanNet and TUM readers on tiny fixtures written by the tests themselves."""

import os
import shutil

import cv2
import numpy as np
import pytest

from jaxfusion import datasets
from jaxfusion.datasets import synthetic
from jaxfusion.datasets.classes import IGNORE_LABEL, NYU40_TO_SCANNET12, SCANNET_CLASS_NAMES

# Our 7 classes written as NYU40 ids: background→wall, bottle→otherprop, chair, table,
# plant→otherprop, sofa, tv→television.
OURS_TO_NYU40 = np.array([1, 40, 5, 7, 40, 6, 25])


@pytest.fixture(scope="module")
def source():
  return synthetic.make_sequence("house", 0, num_frames=3, height=24, width=32, realism=True)


def write_scannet(seq, path):
  for sub in ("color", "depth", "pose", "intrinsic", "label-filt"):
    os.makedirs(os.path.join(path, sub), exist_ok=True)
  for i, f in enumerate(seq):
    big = np.repeat(np.repeat(f.rgb, 2, 0), 2, 1)  # colour at twice the depth resolution
    cv2.imwrite(os.path.join(path, "color", f"{i}.jpg"), big[..., ::-1],
                [cv2.IMWRITE_JPEG_QUALITY, 98])
    cv2.imwrite(os.path.join(path, "depth", f"{i}.png"),
                np.round(f.depth * 1000).astype(np.uint16))
    np.savetxt(os.path.join(path, "pose", f"{i}.txt"), f.T_world_cam.astype(np.float64))
    nyu = np.repeat(np.repeat(OURS_TO_NYU40[f.labels], 2, 0), 2, 1).astype(np.uint16)
    cv2.imwrite(os.path.join(path, "label-filt", f"{i}.png"), nyu)
  K = np.eye(4)
  K[:3, :3] = seq.camera.matrix()
  np.savetxt(os.path.join(path, "intrinsic", "intrinsic_depth.txt"), K)
  return path


def test_scannet_round_trip(source, tmp_path):
  seq = datasets.load_scannet(write_scannet(source, str(tmp_path / "scene0000_00")))
  assert len(seq) == 3 and seq.name == "scene0000_00"
  assert seq.class_names == SCANNET_CLASS_NAMES and seq.info["num_skipped"] == 0
  np.testing.assert_allclose(seq.camera, source.camera, rtol=1e-6)
  np.testing.assert_allclose(seq.depth, source.depth, atol=5e-4)
  np.testing.assert_array_equal(seq.T_world_cam, source.T_world_cam)
  expected = NYU40_TO_SCANNET12[OURS_TO_NYU40[source.labels]]
  np.testing.assert_array_equal(seq.labels, expected)
  assert np.all(seq.labels[source.labels == 0] == IGNORE_LABEL)  # walls are ignored
  assert np.all(seq.labels[source.labels == 2] == SCANNET_CLASS_NAMES.index("chair"))
  assert np.abs(seq.rgb.astype(int) - source.rgb.astype(int)).mean() < 8
  assert len(datasets.load_scannet(str(tmp_path / "scene0000_00"), stride=2)) == 2


def test_scannet_invalid_pose_is_skipped_and_reported(source, tmp_path):
  path = write_scannet(source, str(tmp_path / "s"))
  np.savetxt(os.path.join(path, "pose", "1.txt"), np.full((4, 4), -np.inf))
  with pytest.warns(UserWarning, match="skipped 1 frame"):
    seq = datasets.load_scannet(path)
  assert len(seq) == 2 and seq.info["frame_ids"] == [0, 2]
  assert seq.info["skipped"][0]["reason"].startswith("invalid pose")


def test_scannet_bad_files_name_the_file(source, tmp_path):
  path = write_scannet(source, str(tmp_path / "s"))
  os.remove(os.path.join(path, "color", "2.jpg"))
  with pytest.raises(FileNotFoundError, match=r"color/2\.jpg"):
    datasets.load_scannet(path)
  with pytest.warns(UserWarning, match="skipped 1"):
    assert len(datasets.load_scannet(path, skip_bad=True)) == 2
  shutil.copy(os.path.join(path, "color", "1.jpg"), os.path.join(path, "color", "2.jpg"))
  with open(os.path.join(path, "depth", "0.png"), "wb") as f:
    f.write(b"\x89PNG garbage")
  with pytest.raises(ValueError, match=r"depth/0\.png"):
    datasets.load_scannet(path)
  with pytest.warns(UserWarning, match="skipped 1"):
    seq = datasets.load_scannet(path, skip_bad=True)
  assert len(seq) == 2 and seq.info["skipped"][0]["file"].endswith("depth/0.png")
  intr = os.path.join(path, "intrinsic", "intrinsic_depth.txt")
  with open(intr, "w") as f:
    f.write("1 2 3\n")
  with pytest.raises(ValueError, match="intrinsic_depth.txt"):
    datasets.load_scannet(path, skip_bad=True)
  np.savetxt(intr, np.array([[30.0, 0, 500], [0, 30, 400], [0, 0, 1]]))  # centre off the image
  with pytest.raises(ValueError, match="intrinsic_depth.txt"):
    datasets.load_scannet(path, skip_bad=True)
  shutil.rmtree(os.path.join(path, "pose"))
  with pytest.raises(FileNotFoundError, match="pose"):
    datasets.load_scannet(path)


def _quat(R):
  """(qx, qy, qz, qw) of a rotation matrix (test helper)."""
  w = np.sqrt(max(0.0, 1 + np.trace(R))) / 2
  x = np.copysign(np.sqrt(max(0.0, 1 + R[0, 0] - R[1, 1] - R[2, 2])) / 2, R[2, 1] - R[1, 2])
  y = np.copysign(np.sqrt(max(0.0, 1 - R[0, 0] + R[1, 1] - R[2, 2])) / 2, R[0, 2] - R[2, 0])
  z = np.copysign(np.sqrt(max(0.0, 1 - R[0, 0] - R[1, 1] + R[2, 2])) / 2, R[1, 0] - R[0, 1])
  return np.array([x, y, z, w])


def write_tum(seq, path):
  os.makedirs(os.path.join(path, "rgb"))
  os.makedirs(os.path.join(path, "depth"))
  rgb_lines, depth_lines, gt_lines = ["# color images"], ["# depth maps"], ["# ground truth"]
  for i, f in enumerate(seq):
    t = 100.0 + i * 0.5
    cv2.imwrite(os.path.join(path, "rgb", f"{t + 0.004:.6f}.png"), f.rgb[..., ::-1])
    cv2.imwrite(os.path.join(path, "depth", f"{t:.6f}.png"),
                np.round(f.depth * 5000).astype(np.uint16))
    rgb_lines.append(f"{t + 0.004:.6f} rgb/{t + 0.004:.6f}.png")
    depth_lines.append(f"{t:.6f} depth/{t:.6f}.png")
    T = f.T_world_cam.astype(np.float64)
    q = _quat(T[:3, :3])
    gt_lines.append(f"{t - 0.003:.4f} " + " ".join(f"{v:.9f}" for v in (*T[:3, 3], *q)))
  depth_lines.append("200.000000 depth/200.000000.png")  # no rgb/pose near t = 200
  for name, lines in (("rgb.txt", rgb_lines), ("depth.txt", depth_lines),
                      ("groundtruth.txt", gt_lines)):
    with open(os.path.join(path, name), "w") as f:
      f.write("\n".join(lines) + "\n")
  return path


def test_tum_round_trip_and_unmatched_frames_are_counted(source, tmp_path):
  path = write_tum(source, str(tmp_path / "rgbd_dataset_freiburg1_xyz"))
  with pytest.warns(UserWarning, match="skipped 1"):
    seq = datasets.load_tum(path, camera=source.camera)
  assert len(seq) == 3 and seq.labels is None and seq.info["num_skipped"] == 1
  np.testing.assert_allclose(seq.depth, source.depth, atol=1.01 / 5000 / 2)
  np.testing.assert_array_equal(seq.rgb, source.rgb)
  np.testing.assert_allclose(seq.T_world_cam, source.T_world_cam, atol=1e-5)
  with pytest.warns(UserWarning):
    default = datasets.load_tum(path)
  assert default.camera.fx == pytest.approx(525.0 * 32 / 640)


def test_tum_bad_input(source, tmp_path):
  path = write_tum(source, str(tmp_path / "t"))
  os.remove(os.path.join(path, "rgb", "100.504000.png"))
  with pytest.raises(FileNotFoundError, match="100.504000.png"):
    datasets.load_tum(path)
  with pytest.warns(UserWarning, match="skipped 2"):
    assert len(datasets.load_tum(path, skip_bad=True)) == 2
  with open(os.path.join(path, "groundtruth.txt"), "a") as f:
    f.write("1 2 3\n")
  with pytest.raises(ValueError, match="groundtruth.txt:"):
    datasets.load_tum(path)
  os.remove(os.path.join(path, "depth.txt"))
  with pytest.raises(FileNotFoundError, match="depth.txt"):
    datasets.load_tum(path)
