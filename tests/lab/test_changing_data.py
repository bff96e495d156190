"""The commands' data in a changing world: `jaxfusion run --free-space` saves, exports and scores
the cleared map, `--true-poses` fuses a drifting sequence at its true poses (one line where it
has none), and `lab.sequences` keeps a changing sequence's GT frames when it drops frames or
streams them."""

import dataclasses

import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import datasets
from jaxfusion import metrics
from jaxfusion import sources
from jaxfusion.lab import cli
from jaxfusion.lab import sequences

# Two passes of 8 frames each: enough for the second pass to see through a few voxels that the
# moved objects filled in the first (24×32 and 6 frames clear none).
FRAMES, HEIGHT, WIDTH = 16, 24, 32
SIZE = ["--frames", str(FRAMES), "--height", str(HEIGHT), "--width", str(WIDTH)]


def _predictions(folder, seq):
  """The GT labels, softened: one file a frame."""
  k = len(seq.class_names)
  for t in range(len(seq)):
    probs = 0.2 / k + 0.8 * np.eye(k, dtype=np.float32)[np.maximum(seq.labels[t], 0)]
    sources.save_prediction(folder / f"{t:06d}.npz", mean=probs)


def _main(argv, capsys):
  code = cli.main(argv)
  out, err = capsys.readouterr()
  return code, out, err


def _coords(voxels) -> set:
  return {tuple(c) for c in np.asarray(voxels["coords"]).tolist()}


def _ghost(seq) -> set:
  """Voxels that the moved and removed objects filled in pass 1 and the final scene does not."""
  t1 = seq.info["gt_frames"][0]
  record = seq.info["changes"]
  gone = np.isin(seq.instances, record["moved"] + record["removed"])
  first = dataclasses.replace(seq, labels=np.where(gone, seq.labels, -1),
                              info=dict(seq.info, gt_frames=[0, t1]))
  return _coords(datasets.gt_voxel_labels(first)) - _coords(datasets.gt_voxel_labels(seq))


def _ply_vertices(path) -> int:
  with open(path, "rb") as f:
    header = f.read(1024).split(b"end_header")[0].decode("ascii")
  return next(int(line.split()[-1]) for line in header.splitlines()
              if line.startswith("element vertex"))


@pytest.mark.slow
def test_run_with_free_space_saves_and_shows_the_cleared_map(tmp_path, capsys):
  seq = datasets.load_spec("office:0:moved", num_frames=FRAMES, height=HEIGHT, width=WIDTH)
  _predictions(tmp_path / "pred", seq)
  argv = ["run", "--data", "office:0:moved", *SIZE, "--rule", "bayes", "--predictions",
          str(tmp_path / "pred"), "--no-geometry", "--out", str(tmp_path / "out")]
  maps = {}
  for free in (False, True):
    code, out, _ = _main(argv + (["--free-space"] if free else []), capsys)
    assert code == 0
    stem = tmp_path / "out" / ("office_0_test_moved_bayes" + ("_free" if free else ""))
    state, _, meta = jf.io.load_map(f"{stem}.npz")          # the file keeps the layer
    voxels = jf.read_map(state)
    assert meta["extra"]["free_space"] is free and (state.free_space is not None) is free
    assert _ply_vertices(f"{stem}.ply") == 8 * len(voxels["coords"])   # a cube per voxel
    maps[free] = state, voxels, out
  (_, plain, _), (cleared, voxels, out) = maps[False], maps[True]
  free = jf.map_stats(cleared)["free"]
  assert free > 0 and f"map: {len(voxels['coords'])} voxels ({free} stored voxels cleared" in out
  assert len(voxels["coords"]) + free == len(plain["coords"])
  ghost = _ghost(seq)
  assert len(ghost & _coords(voxels)) < len(ghost & _coords(plain))


@pytest.mark.slow   # an end-to-end `run` with predictions, evaluation and a saved map (~15 s)
def test_true_poses_fuse_a_drifting_sequence_where_it_was(tmp_path, capsys):
  seq = datasets.load_spec("office:0:drift", num_frames=4, height=HEIGHT, width=WIDTH)
  true_poses = np.asarray(seq.info["true_poses"], np.float32)
  assert np.abs(true_poses - seq.T_world_cam).max() > 1e-3       # the stored poses drift
  _predictions(tmp_path / "pred", seq)
  code, _, _ = _main(["run", "--data", "office:0:drift", "--frames", "4", "--height",
                      str(HEIGHT), "--width", str(WIDTH), "--rule", "bayes", "--predictions",
                      str(tmp_path / "pred"), "--no-geometry", "--true-poses", "--out",
                      str(tmp_path)], capsys)
  assert code == 0
  path = str(tmp_path / "office_0_test_drift_bayes_true_poses.npz")
  np.testing.assert_array_equal(jf.io.load_trajectory(path)["T_world_cam"], true_poses)
  state, _, meta = jf.io.load_map(path)
  assert meta["extra"]["true_poses"] is True
  # Fused where the frames were, the map holds every GT voxel (GT is of the true poses).
  ev = metrics.evaluate_map(jf.read_map(state), datasets.gt_voxel_labels(seq),
                            len(seq.class_names), ignore_label=datasets.IGNORE_LABEL)
  assert ev["gt_only"] == 0 and ev["accuracy"] > 0.99


def test_true_poses_are_refused_for_a_sequence_without_them(tmp_path, capsys):
  code, _, err = _main(["run", "--data", "office:0", "--frames", "2", "--height", str(HEIGHT),
                        "--width", str(WIDTH), "--true-poses", "--out", str(tmp_path)], capsys)
  lines = [line for line in err.splitlines() if line.startswith("jaxfusion")]
  assert code == 2 and len(lines) == 1
  assert "--true-poses: office:0 has no true poses" in lines[0] and "Traceback" not in err


def test_loaded_and_streamed_gt_of_a_moved_sequence_with_a_frame_skipped(tmp_path):
  seq = datasets.load_spec("office:0:moved", num_frames=6, height=HEIGHT, width=WIDTH)
  seq.save(str(tmp_path / "moved"))
  _predictions(tmp_path / "pred" / "moved", seq)
  (tmp_path / "pred" / "moved" / "000004.npz").unlink()        # frame 4 (pass 2) has none
  keep = [0, 1, 2, 3, 5]
  want = datasets.gt_voxel_labels(seq.subset(keep))              # pass 2: frames 3 and 5
  options = sequences.DataOptions(predictions=str(tmp_path / "pred"), missing="skip")
  item = sequences.load(f"saved:{tmp_path / 'moved'}", options)
  assert item.sequence.info["gt_frames"] == [3, 5] and item.sequence.info["frame_ids"] == keep
  streamed = sequences.Streamed(f"saved:{tmp_path / 'moved'}", options, chunk=2).gt()
  for got in (item.gt, streamed):
    for key in ("coords", "labels", "hits"):
      np.testing.assert_array_equal(got[key], want[key])
