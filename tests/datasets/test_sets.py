"""Sets of sequences (`datasets.sets`) and the embedded spec's layout seed and shift."""

import os

import pytest

from jaxfusion import datasets
from jaxfusion.datasets import sets
from jaxfusion.datasets.specs import SequenceSpec


@pytest.mark.parametrize("text,seed,shift,domain", [
    ("office:0", None, None, "test"), ("office:0:s1", 1, None, "test"),
    ("house:2:train:s11:shift0.5", 11, 0.5, "train"), ("office:1:shift0.25:s3", 3, 0.25, "test"),
    ("synthetic:office/1/train", None, None, "train")])
def test_embedded_specs_carry_seed_and_shift(text, seed, shift, domain):
  spec = datasets.parse_spec(text)
  assert (spec.layout_seed, spec.shift, spec.domain) == (seed, shift, domain)
  assert datasets.parse_spec(str(spec)) == spec          # the printed spec reads back


@pytest.mark.parametrize("text", ["office:0:s1:s2", "office:0:shift2", "office:0:shiftx",
                                  "office:3", "office:0:foo", "office:0:train:test"])
def test_bad_embedded_specs_name_the_syntax(text):
  with pytest.raises(ValueError, match="sSEED"):
    datasets.parse_spec(text)


def test_resolved_fills_only_what_the_spec_leaves_open():
  spec = datasets.parse_spec("office:0:s4")
  assert spec.resolved(layout_seed=9, shift=0.5) == spec._replace(layout_seed=4, shift=0.5)
  folder = datasets.parse_spec("scannet:/x")
  assert folder.resolved(layout_seed=9) == folder


def test_load_spec_uses_the_spec_seed_over_the_default():
  a = datasets.load_spec("office:0:s2:shift0", num_frames=1, height=12, width=16, layout_seed=0)
  b = datasets.load_spec("office:0", num_frames=1, height=12, width=16, layout_seed=2, shift=0.0)
  assert (a.rgb == b.rgb).all() and (a.depth == b.depth).all()


def _folders(root, names):
  for n in names:
    os.makedirs(os.path.join(root, n))
  return [os.path.join(root, n) for n in names]


def test_expand_specs_patterns_and_list_files(tmp_path):
  a, b, _ = _folders(str(tmp_path), ["scene0000_00", "scene0001_00", "other"])
  listing = tmp_path / "lists" / "set.txt"
  listing.parent.mkdir()
  listing.write_text("# my set\nscannet:../scene0001_00   # relative to the file\n\n"
                     "office:0:s5\n")
  got = sets.expand([f"scannet:{tmp_path}/scene00*", "house:1:s6"])
  assert [str(s) for s in got] == [f"scannet:{a}", f"scannet:{b}", "house:1:s6"]
  got = sets.expand([f"@{listing}"])
  assert [str(s) for s in got] == [f"scannet:{os.path.join(str(listing.parent), '../scene0001_00')}",
                                   "office:0:s5"]
  assert [str(s) for s in sets.expand([str(listing)])] == [str(s) for s in got]


@pytest.mark.parametrize("items,match", [
    (["scannet:/no/such/dir/scene*"], "no folder matches"), (["office:0", "office:0"], "twice"),
    ([], "names no sequence"), (["office:9"], "--data: an embedded sequence")])
def test_expand_refuses_in_one_line(items, match):
  with pytest.raises(ValueError, match=match):
    sets.expand(items)


def test_expand_refuses_an_empty_or_missing_list(tmp_path):
  empty = tmp_path / "empty.txt"
  empty.write_text("# nothing\n")
  with pytest.raises(ValueError, match="names none"):
    sets.expand([str(empty)])
  with pytest.raises(FileNotFoundError, match="no such list"):
    sets.expand(["@" + str(tmp_path / "missing.txt")])


def test_overlapping_sets_are_refused(tmp_path):
  a, b = _folders(str(tmp_path), ["s0", "s1"])
  cal = sets.expand([f"scannet:{a}", "office:0:s11"])
  sets.check_disjoint({"--calibration-data": cal, "--data": sets.expand([f"saved:{b}"]),
                       "--validation-data": None})
  with pytest.raises(ValueError, match="--calibration-data and --data share .*s0"):
    sets.check_disjoint({"--calibration-data": cal,
                         "--data": sets.expand([f"tum:{tmp_path}/s0/"])})   # the same folder
  with pytest.raises(ValueError, match="share layout seed 11"):   # another trajectory, same room
    sets.check_disjoint({"--calibration-data": cal, "--data": sets.expand(["house:2:s11"])})


def test_embedded_set_names_the_grid():
  got = sets.embedded_set(["office", "house"], [0], [1, 2], [0.0, 1.0])
  assert [str(s) for s in got][:3] == ["office:0:s1:shift0", "office:0:s1:shift1",
                                       "house:0:s1:shift0"]
  assert len(got) == 8


def test_prediction_folders_are_named_after_the_sequence(tmp_path):
  spec = SequenceSpec("scannet", path="/data/scans/scene0000_00/")
  assert sets.sequence_name(spec) == "scene0000_00"
  (tmp_path / "scene0000_00").mkdir()
  assert sets.predictions_folder(str(tmp_path), spec) == str(tmp_path / "scene0000_00")
  embedded = datasets.parse_spec("office:0:s1:shift0.5")
  with pytest.raises(FileNotFoundError, match="office_0_test_s1_shift0.5"):
    sets.predictions_folder(str(tmp_path), embedded)
  (tmp_path / "office_0_test").mkdir()                      # the tuning commands' older layout
  assert sets.predictions_folder(str(tmp_path), embedded) == str(tmp_path / "office_0_test")


def test_a_changing_world_never_shares_a_name_or_folder_with_its_static_one(tmp_path):
  names = {text: sets.sequence_name(sets.expand([text])[0]) for text in (
      "office:0:s1", "office:0:s1:moved", "office:0:moved:s1", "office:0:s1:final",
      "office:0:s1:drift", "office:0:s1:shift0.5:drift")}
  assert names["office:0:s1:moved"] == names["office:0:moved:s1"] == "office_0_test_s1_moved"
  assert names["office:0:s1:shift0.5:drift"] == "office_0_test_s1_shift0.5_drift"
  assert len(set(names.values())) == len(names) - 1           # only the two spellings agree
  (tmp_path / "office_0_test").mkdir()                        # the static sequence's folder
  moved = datasets.parse_spec("office:0:moved")
  with pytest.raises(FileNotFoundError, match="office_0_test_moved"):
    sets.predictions_folder(str(tmp_path), moved)
  (tmp_path / "office_0_test_moved").mkdir()                  # its own name (`seq.name`)
  assert sets.predictions_folder(str(tmp_path), moved) == str(tmp_path / "office_0_test_moved")
  assert sets.predictions_folder(str(tmp_path), datasets.parse_spec("office:0")) == str(
      tmp_path / "office_0_test")
