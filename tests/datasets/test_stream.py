"""Sequences read chunk by chunk (`datasets.stream`): the same frames as a whole read."""

import numpy as np
import pytest

from jaxfusion import datasets
from jaxfusion.datasets import export
from jaxfusion.datasets import ground_truth
from jaxfusion.datasets import stream


@pytest.fixture(scope="module")
def embedded():
  return datasets.make_sequence("office", 0, num_frames=5, height=24, width=32, seed=3)


def _joined(chunks):
  chunks = list(chunks)
  return (np.concatenate([c.depth for c in chunks]),
          np.concatenate([c.T_world_cam for c in chunks]),
          [i for c in chunks for i in c.info["frame_ids"]], [len(c) for c in chunks])


@pytest.mark.parametrize("kind", ["saved", "scannet", "tum", "embedded"])
@pytest.mark.parametrize("stride", [1, 2])
def test_chunks_are_the_whole_read(kind, stride, embedded, tmp_path):
  path = str(tmp_path / "seq")
  if kind == "saved":
    embedded.save(path)
  elif kind == "scannet":
    export.save_scannet(embedded, path, color_size=(48, 64))
  elif kind == "tum":
    export.save_tum(embedded, path)
  spec = "office:0:s3" if kind == "embedded" else f"{kind}:{path}"
  kw = dict(num_frames=5, height=24, width=32) if kind == "embedded" else dict(stride=stride)
  whole = datasets.load_spec(spec, label_space="embedded", **kw)
  s = stream.open_stream(spec, label_space="embedded", **kw)
  assert len(s) == len(whole)
  depth, poses, ids, sizes = _joined(s.chunks(2))
  np.testing.assert_array_equal(depth, whole.depth)
  np.testing.assert_array_equal(poses, whole.T_world_cam)
  assert sizes == [2] * (len(whole) // 2) + ([1] if len(whole) % 2 else [])
  if kind != "embedded":
    assert ids == list(whole.info["frame_ids"])
  first = s.first()
  assert len(first) == 1 and first.camera == whole.camera


def test_stream_of_a_missing_folder_or_a_bad_chunk(tmp_path):
  with pytest.raises(FileNotFoundError, match="no such folder"):
    stream.open_stream(f"scannet:{tmp_path}/none")
  (tmp_path / "meta.json").write_text('{"num_frames": 0}')
  with pytest.raises(ValueError, match="no readable frames"):
    stream.open_stream(f"saved:{tmp_path}")


def _same_gt(got, want):
  for key in ("coords", "labels", "hits"):
    np.testing.assert_array_equal(got[key], want[key])


@pytest.mark.slow
@pytest.mark.parametrize("change", ["moved", "drift"])
def test_streamed_gt_of_a_changing_world_is_its_gt(change, tmp_path):
  # Chunks of 2 of 6 frames: the moved sequence's chunk 1 straddles the passes (t1 = 3).
  size = dict(num_frames=6, height=24, width=32)
  whole = datasets.load_spec(f"office:0:s3:{change}", **size)
  want = datasets.gt_voxel_labels(whole)
  whole.save(str(tmp_path / "seq"))
  for spec in (f"office:0:s3:{change}", f"saved:{tmp_path / 'seq'}"):
    chunks = list(stream.open_stream(spec, **size).chunks(2))
    got = ground_truth.gt_from_frames(map(ground_truth.gt_part, chunks), camera=whole.camera,
                                      num_classes=whole.num_classes)
    _same_gt(got, want)
  everything = ground_truth.gt_from_frames(chunks, camera=whole.camera,
                                           num_classes=whole.num_classes)
  assert len(everything["coords"]) != len(want["coords"])   # what gt_part leaves out counts
