"""`jaxfusion learn-rule` end to end on small stand-in batches: the seeds it refuses, the files it
writes, and that `learn.load_params` gives back the rule it fitted."""

import argparse
import json

import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import learn
from jaxfusion.lab import cli
from jaxfusion.lab import learning
from jaxfusion.lab import tuning
from tests.library.test_tune import batch_of


@pytest.fixture(scope="module")
def batches():
  return {11: batch_of([0]), 12: batch_of([1]), 13: batch_of([2])}


@pytest.mark.slow
def test_learn_rule_command_writes_params_record_and_figures(batches, tmp_path, monkeypatch):
  seen = []

  def load(units, **kwargs):
    seen.append((tuple(units), kwargs["shift"], kwargs["front_end"]))
    return batches[units[0][2]]

  monkeypatch.setattr(tuning, "load_sequence_batch", load)
  parser = argparse.ArgumentParser()
  learning.add_parser(parser.add_subparsers())
  out = tmp_path / "rule"
  args = parser.parse_args(["learn-rule", "--envs", "office", "--trajectories", "0",
                            "--train-seeds", "11", "12", "--validation-seeds", "13",
                            "--shifts", "0.5", "1.0", "--steps", "4", "--eval-every", "2",
                            "--front-end", "simulated", "--voxel-size", "0.25",
                            "--out", str(out)])
  assert args.func(args) == 0
  # Training: seeds 11 and 12 at both shifts in one batch; validation: seed 13 at both.
  assert [(u, s) for u, s, _ in seen] == [
      ((("office", 0, 11), ("office", 0, 12)), 0.5), ((("office", 0, 11), ("office", 0, 12)), 1.0),
      ((("office", 0, 13),), 0.5), ((("office", 0, 13),), 1.0)]
  record = json.loads((out / "record.json").read_text())
  assert record["steps_run"] == 4 and len(record["train_losses"]) == 4
  assert [step for step, _ in record["validation"]] == [0, 2, 4]
  # The stand-in loader gives one sequence a call: one per shift in each split.
  assert len(record["data"]["train"]) == 2 and len(record["data"]["validation"]) == 2
  assert record["seconds"]["fit"] > 0
  params = learn.load_params(str(out / "params.json"))
  assert params == record["params"]
  rule = jf.rules.learned(params)
  assert rule.name == "learned" and np.shape(params["beta"]) == (4,)
  for name in ("loss.png", "weights.png"):
    assert (out / name).stat().st_size > 1000


@pytest.mark.slow
def test_learn_rule_fits_the_family_from_a_glfs_table(batches, tmp_path, monkeypatch):
  monkeypatch.setattr(tuning, "load_sequence_batch", lambda units, **kw: batches[units[0][2]])
  table = np.random.default_rng(0).uniform(0.3, 3.0, (4, 5, 4))
  start = tmp_path / "glfs.json"
  start.write_text(json.dumps({"rule": "glfs", "params": {"table": table.tolist()}}))
  parser = argparse.ArgumentParser()
  learning.add_parser(parser.add_subparsers())
  out = tmp_path / "family"
  args = parser.parse_args(["learn-rule", "--family", "family", "--terms", "moments", "mix",
                            "--start-table", str(start), "--envs", "office", "--trajectories",
                            "0", "--train-seeds", "11", "--validation-seeds", "13", "--shifts",
                            "1.0", "--steps", "2", "--eval-every", "1", "--front-end",
                            "simulated", "--voxel-size", "0.25", "--out", str(out)])
  assert args.func(args) == 0
  family, params = learn.load_rule(str(out / "params.json"))
  assert family == "family" and set(jf.rules.family_lib.terms(params)) == {
      "table", "moments", "mix"}
  record = json.loads((out / "record.json").read_text())
  assert "--start-table" in record["command"] and "--terms moments mix" in record["command"]
  # A start that has no table is refused in one line.
  bad = tmp_path / "learned.json"
  bad.write_text(json.dumps({"rule": "learned", "params": {}}))
  assert cli.main(["learn-rule", "--family", "family", "--start-table", str(bad), "--out",
                   str(tmp_path / "x")]) == 2


def test_learn_rule_refuses_overlapping_or_judged_seeds(tmp_path, capsys):
  for argv, match in ((["--train-seeds", "11", "--validation-seeds", "11"], "disjoint"),
                      (["--train-seeds", "2", "12"], "judged on")):
    assert cli.main(["learn-rule", *argv, "--out", str(tmp_path)]) == 2
    assert match in capsys.readouterr().err


def test_load_params_rejects_other_files(tmp_path):
  path = tmp_path / "p.json"
  path.write_text(json.dumps({"beta": 0.3}))
  with pytest.raises(ValueError, match="not a learned-rule parameter file"):
    learn.load_params(str(path))
  path.write_text(json.dumps({"params": {"mix": 3.0}}))
  with pytest.raises(ValueError, match="mix must lie"):
    learn.load_params(str(path))


def test_recorded_command_line_parses_back_to_the_same_options():
  parser = cli.build_parser()
  args = parser.parse_args(["learn-rule", "--frames", "30", "--shifts", "0.5", "1.0",
                            "--train-seeds", "11", "12", "--scalar-beta", "--select", "miou",
                            "--out", "x"])
  line = learning.command_line(args)
  assert line.startswith("jaxfusion learn-rule --") and "--shifts 0.5 1.0" in line
  again = parser.parse_args(line.split()[1:])
  assert vars(again) == vars(args)
