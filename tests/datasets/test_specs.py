"""The one sequence syntax of every command (`datasets.parse_spec` / `load_spec`)."""

import numpy as np
import pytest

from jaxfusion import datasets
from jaxfusion.datasets import specs


@pytest.mark.parametrize("text,parsed,canonical", [
    ("office:0", ("synthetic", "office", 0, "test", None), "office:0"),
    ("house:2:train", ("synthetic", "house", 2, "train", None), "house:2:train"),
    ("synthetic:office/1", ("synthetic", "office", 1, "test", None), "office:1"),
    ("synthetic:house/0/train", ("synthetic", "house", 0, "train", None), "house:0:train"),
    ("scannet:/data/scene0006_00", ("scannet", None, None, None, "/data/scene0006_00"),
     "scannet:/data/scene0006_00"),
    ("tum:rgbd/fr1", ("tum", None, None, None, "rgbd/fr1"), "tum:rgbd/fr1"),
    ("saved:seqs/house_2", ("saved", None, None, None, "seqs/house_2"), "saved:seqs/house_2"),
])
def test_parse(text, parsed, canonical):
  spec = datasets.parse_spec(text)
  assert tuple(spec)[:5] == parsed and str(spec) == canonical
  assert spec.layout_seed is None and spec.shift is None
  assert datasets.parse_spec(str(spec)) == spec


@pytest.mark.parametrize("text,match", [
    ("office", "ENV:TRAJECTORY"), ("office:3", "TRAJECTORY 0|1|2"), ("kitchen:0", "ENV:TRAJ"),
    ("office:0:dev", "DOMAIN"), ("synthetic:office", "synthetic:ENV/TRAJECTORY"),
    ("scannet:", "needs a folder"), ("", "non-empty"),
])
def test_bad_specs_say_the_syntax(text, match):
  with pytest.raises(ValueError, match=match):
    datasets.parse_spec(text)


def test_load_embedded_saved_and_missing(tmp_path):
  seq = datasets.load_spec("office:1", num_frames=3, height=12, width=16, layout_seed=2)
  ref = datasets.make_sequence("office", 1, num_frames=3, height=12, width=16, seed=2)
  assert seq.name == "office_1_test" and np.array_equal(seq.rgb, ref.rgb)
  assert specs.unit_name(seq.name, 2) == "office_1_test_s2"
  seq.save(str(tmp_path / "s"))
  again = datasets.load_spec(f"saved:{tmp_path / 's'}", num_frames=2, stride=2)
  assert len(again) == 2 and np.array_equal(again.depth[1], seq.depth[2])
  with pytest.raises(FileNotFoundError, match="no such folder"):
    datasets.load_spec("tum:/no/such/folder")
