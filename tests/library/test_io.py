"""Map save/load round-trips bit-exactly; the PLY re-loads with trimesh with the right colours."""

import json
import os

import jax
import numpy as np
import pytest
import trimesh

import jaxfusion as jf
from jaxfusion import io
from tests import engine_helpers as h


@pytest.mark.parametrize("name", ["sum_labels", "robust_dr"])
def test_save_load_round_trip_is_bit_exact(tmp_path, name):
  rng = np.random.default_rng(0)
  rule = jf.rules.by_name(name, **h.rule_kwargs(name, beta=0.2, aggregate="mean"))
  state = jf.init_map(capacity=256, num_classes=h.NUM_CLASSES, voxel_size=0.25, rule=rule)
  for _ in range(2):
    state = jf.fuse_frame(state, h.random_frame(rng), h.CAMERA, rule)
  path = str(tmp_path / "map.npz")
  io.save_map(path, state, rule, class_names=["a", "b", "c", "d"], extra={"seq": "x"})
  loaded, loaded_rule, meta = io.load_map(path)
  for a, b in zip(jax.tree.leaves(state), jax.tree.leaves(loaded)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert np.asarray(a).dtype == np.asarray(b).dtype
  assert loaded.rule_name == state.rule_name and loaded.max_probes == state.max_probes
  assert loaded_rule.aggregate == "mean"
  assert jax.tree.map(float, loaded_rule.hparams) == jax.tree.map(float, rule.hparams)
  assert meta["class_names"] == ["a", "b", "c", "d"] and meta["extra"] == {"seq": "x"}
  # The loaded map keeps fusing exactly like the original.
  frame = h.random_frame(rng)
  a = jf.read_map(jf.fuse_frame(state, frame, h.CAMERA, rule))
  b = jf.read_map(jf.fuse_frame(loaded, frame, h.CAMERA, loaded_rule))
  np.testing.assert_array_equal(a["posterior"], b["posterior"])
  assert not [f for f in os.listdir(tmp_path) if f.startswith(".tmp-")]


def test_load_refuses_other_files(tmp_path):
  bad = tmp_path / "bad.npz"
  np.savez(bad, x=np.zeros(3))
  with pytest.raises(ValueError, match="not a jaxfusion map"):
    io.load_map(str(bad))
  with pytest.raises(FileNotFoundError):
    io.load_map(str(tmp_path / "missing.npz"))


@pytest.mark.parametrize("mode", ["points", "cubes"])
def test_ply_reloads_with_class_colours(tmp_path, mode):
  voxels = {"coords": np.array([[0, 0, 0], [1, 2, 3], [-4, 0, 1]], np.int32),
            "labels": np.array([2, 0, 1])}
  colors = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8)
  path = str(tmp_path / f"map_{mode}.ply")
  io.export_ply(path, voxels, voxel_size=0.1, colors=colors, mode=mode)
  loaded = trimesh.load(path, process=False)
  vertex_colors = np.asarray(loaded.colors if mode == "points" else
                             loaded.visual.vertex_colors)[:, :3]
  per_voxel = 1 if mode == "points" else 8
  assert len(vertex_colors) == 3 * per_voxel
  np.testing.assert_array_equal(vertex_colors[::per_voxel], colors[voxels["labels"]])
  centers = np.asarray(loaded.vertices).reshape(3, per_voxel, 3).mean(axis=1)
  np.testing.assert_allclose(centers, (voxels["coords"] + 0.5) * 0.1, atol=1e-6)


def test_written_files_get_ordinary_permissions(tmp_path):
  # mkstemp would leave 0600; the result must match what a plain open() creates.
  (tmp_path / "plain.txt").write_text("x")
  io.atomic_write(str(tmp_path / "atomic.txt"), lambda tmp: open(tmp, "w").write("x"))
  mode = lambda name: os.stat(tmp_path / name).st_mode & 0o777
  assert mode("atomic.txt") == mode("plain.txt")


def _small_map(rng):
  rule = jf.rules.bayes()
  state = jf.init_map(capacity=128, num_classes=h.NUM_CLASSES, voxel_size=0.25, rule=rule)
  return jf.fuse_frame(state, h.random_frame(rng), h.CAMERA, rule), rule


def test_trajectory_round_trip(tmp_path):
  rng = np.random.default_rng(1)
  state, rule = _small_map(rng)
  poses = np.stack([h.pose(rng) for _ in range(3)]).astype(np.float32)
  path = str(tmp_path / "map.npz")
  io.save_map(path, state, rule, poses=poses, camera=h.CAMERA, image_size=(h.HEIGHT, h.WIDTH))
  traj = io.load_trajectory(path)
  np.testing.assert_array_equal(traj["T_world_cam"], poses)
  assert traj["camera"] == {"fx": 6.0, "fy": 6.0, "cx": 3.5, "cy": 2.5, "height": h.HEIGHT,
                            "width": h.WIDTH}
  loaded, _, meta = io.load_map(path)   # poses do not disturb the map itself
  np.testing.assert_array_equal(np.asarray(loaded.keys), np.asarray(state.keys))
  io.save_map(path, state, rule, poses=poses)   # poses without intrinsics
  assert io.load_trajectory(path)["camera"] is None


def test_maps_without_poses_still_load(tmp_path):
  rng = np.random.default_rng(2)
  state, rule = _small_map(rng)
  path = str(tmp_path / "map.npz")
  io.save_map(path, state, rule)
  assert io.load_trajectory(path) is None
  # A file written before poses existed: no "camera" entry in its metadata at all.
  with np.load(path) as f:
    arrays = dict(f)
  meta = json.loads(bytes(arrays["metadata"]).decode())
  del meta["camera"]
  arrays["metadata"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
  old = str(tmp_path / "old.npz")
  np.savez(old, **arrays)
  loaded, _, _ = io.load_map(old)
  np.testing.assert_array_equal(np.asarray(loaded.keys), np.asarray(state.keys))
  assert io.load_trajectory(old) is None
  with pytest.raises(ValueError, match="not a jaxfusion map"):
    np.savez(tmp_path / "other.npz", x=np.zeros(2))
    io.load_trajectory(str(tmp_path / "other.npz"))


@pytest.mark.parametrize("kwargs, match", [
    ({"poses": np.eye(4)}, r"\(T, 4, 4\)"),
    ({"poses": np.full((1, 4, 4), np.nan)}, "finite"),
    ({"camera": (1.0, 1.0, 0.0, 0.0), "image_size": (2, 2)}, "pass poses too"),
    ({"poses": np.eye(4)[None], "camera": (1.0, 1.0, 0.0, 0.0)}, "image_size"),
    ({"poses": np.eye(4)[None], "camera": (0.0, 1.0, 0.0, 0.0), "image_size": (2, 2)}, "fx"),
])
def test_save_map_rejects_bad_trajectories(tmp_path, kwargs, match):
  state, rule = _small_map(np.random.default_rng(3))
  with pytest.raises(ValueError, match=match):
    io.save_map(str(tmp_path / "m.npz"), state, rule, **kwargs)
  assert not os.path.exists(tmp_path / "m.npz")
