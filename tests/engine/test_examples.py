"""The examples in the engine's docstrings run as written, and small public helpers."""

import doctest

import numpy as np
import pytest

import jaxfusion as jf
from jaxfusion import batch
from jaxfusion import fusion


@pytest.mark.parametrize("fn", [fusion.fuse_frame, batch.rule_grid], ids=lambda f: f.__name__)
def test_docstring_example_runs(fn):
  finder = doctest.DocTestFinder(recurse=False)
  tests = finder.find(fn, fn.__name__, globs={"np": np, "rule_grid": batch.rule_grid})
  assert tests and tests[0].examples, "the docstring has no example"
  runner = doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
  for test in tests:
    runner.run(test)
  assert runner.summarize(verbose=False).failed == 0


@pytest.mark.parametrize("voxels,load,expected", [
    (0, 0.25, 1024), (256, 0.25, 1024), (257, 0.25, 2048), (1000, 0.25, 4096),
    (1000, 0.5, 2048), (30000, 0.25, 131072), (5, 1.0, 1024)])
def test_capacity_for(voxels, load, expected):
  capacity = jf.capacity_for(voxels, load=load)
  assert capacity == expected and capacity & (capacity - 1) == 0
  assert voxels <= load * capacity


def test_capacity_for_rejects_a_bad_load():
  with pytest.raises(ValueError, match="load"):
    jf.capacity_for(10, load=0.0)
