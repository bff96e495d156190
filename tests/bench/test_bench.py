"""The benchmark code runs on a tiny configuration, and its NumPy peer fuses as the engine does.

No timings are asserted here: `python -m bench` measures them (bench/RESULTS.md).
"""

import json

import numpy as np
import pytest

import jaxfusion as jf
from bench import numpy_peer
from bench import scene
from tests import engine_helpers

# The benchmarks' smoke tests, each a whole bench at a tiny size. The slow tier.
pytestmark = pytest.mark.slow


@pytest.mark.parametrize("rule_name", numpy_peer.RULES)
@pytest.mark.parametrize("aggregate", ["sum", "mean"])
def test_numpy_peer_matches_the_engine(rule_name, aggregate):
  frames = scene.make_frames(3, height=24, width=32, num_classes=7, seed=1)
  # Pixels within float rounding of a voxel face could land in different voxels in XLA and NumPy.
  for t in range(3):
    frames.depth[t] = engine_helpers.drop_ambiguous_pixels(
        frames.depth[t], frames.poses[t], frames.camera, 0.25)
  rule = jf.rules.by_name(rule_name, aggregate=aggregate)
  state = jf.init_map(capacity=2**12, num_classes=7, voxel_size=0.25, rule=rule)
  peer = numpy_peer.NumpyMap(7, rule_name, voxel_size=0.25, aggregate=aggregate)
  for t in range(3):
    state = jf.fuse_frame(state, frames.frame(t), frames.camera, rule)
    peer.fuse(frames.depth[t], frames.poses[t], frames.probs[t], frames.var[t], frames.camera)
  out = jf.read_map(state)
  keys, posterior = peer.posteriors()
  order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0]))
  np.testing.assert_array_equal(out["coords"], keys[order])
  np.testing.assert_allclose(out["posterior"], posterior[order], rtol=2e-3, atol=2e-5)
  np.testing.assert_array_equal(out["hits"], peer.hits[:peer.size][order])


@pytest.mark.slow
def test_bench_suite_runs_on_a_tiny_configuration(tmp_path):
  from bench import suite  # pylint: disable=import-outside-toplevel
  results = suite.run(suite.Config.tiny(), out_dir=tmp_path)
  data = json.loads((tmp_path / "results.json").read_text())
  assert data["throughput"] and data["device"]
  assert (tmp_path / "results.md").exists()
  assert results["throughput"][0]["frames_per_s"] > 0
  (row,) = data["pipeline"]
  assert (row["height"], row["width"], row["M"], row["frames_per_call"]) == (24, 32, 2, 2)
  shares = [row[f"{stage}_share"] for stage in ("sample", "moments", "fuse")]
  assert all(0 < x < 1 for x in shares) and abs(sum(shares) - 1) < 1e-9
  assert row["end_to_end_ms_per_frame"] == pytest.approx(
      row["sample_ms_per_frame"] + row["moments_ms_per_frame"] + row["fuse_ms_per_frame"])
  floor = data["floor"]
  assert floor["floor_ms"] == min(floor["forms_ms"].values()) > 0
  assert floor["dr_over_floor"] == pytest.approx(floor["dr_core_ms"] / floor["floor_ms"])
  assert all(data["loops"][f"{way}_ms_per_frame"] > 0
             for way in ("loop", "sequence", "sequence_core", "batch"))
  assert data["aligned"]["occupied"] > 0
  (sampler,) = data["sampler"]
  assert sampler["speedup"] == pytest.approx(sampler["full_passes_ms"] / sampler["shared_ms"])
  assert {r["num_classes"] for r in data["numpy_peer"]} == {13}
  text = (tmp_path / "results.md").read_text()
  assert "× the floor" in text and "full passes ms" in text and "fuse_sequence core" in text
  assert all(r["numpy_sum0_ms"] > 0 for r in data["mc_moments"])
  assert "The whole pipeline" in (tmp_path / "results.md").read_text()


def test_micro_benchmarks_run_on_tiny_sizes():
  from bench import micro  # pylint: disable=import-outside-toplevel
  terms = micro.terms(repeats=1, num_pixels=64, num_classes=3, blocks=2)
  moments = micro.moments(repeats=1, num_samples=2, height=3, width=4, num_classes=3)
  outer = micro.outer_jit(repeats=1, num_frames=2, height=12, width=16, capacity=2**10)
  assert len(outer) == 2 and all(lo > 0 for lo, _ in outer.values())
  assert len(terms) == 4 and len(moments) == 5
  assert all(0 < lo <= med for lo, med in list(terms.values()) + list(moments.values()))


def _face_shares(frames, voxel_size=0.1, within=0.005):
  """Share of valid pixels whose world point lies within `within` m of a voxel face, per axis."""
  points = []
  for t in range(frames.depth.shape[0]):
    cam_points = np.asarray(jf.camera.backproject(frames.depth[t], frames.camera)).reshape(-1, 3)
    world = cam_points @ frames.poses[t][:3, :3].T + frames.poses[t][:3, 3]
    points.append(world[frames.depth[t].reshape(-1) > 0])
  frac = np.mod(np.concatenate(points) / voxel_size, 1.0)
  near = np.minimum(frac, 1.0 - frac) * voxel_size < within
  return near.mean(axis=0)


def test_bench_room_lies_off_the_voxel_grid():
  # Real rooms are not aligned with the voxel grid: the bench's walls, floor and box faces sit
  # at a sub-voxel offset, so the share of surface points within 5 mm of a face is near the
  # unaligned 10 % on every axis; the aligned stress case puts the floor (and walls) on faces.
  kwargs = dict(height=48, width=64, num_classes=7, seed=2, hole_fraction=0.0)
  off = _face_shares(scene.make_frames(4, **kwargs))
  on = _face_shares(scene.make_frames(4, aligned=True, **kwargs))
  assert np.all(off < 0.15), off
  assert np.max(on) > 0.2, on


@pytest.mark.slow   # six rules compiled end to end: 20 s, most of it compile
def test_context_bench_runs_on_tiny_frames(tmp_path):
  from bench import context as context_bench  # pylint: disable=import-outside-toplevel
  results = context_bench.run(num_frames=2, height=24, width=32, num_classes=5, repeats=1,
                              capacity=2**12)
  assert set(results["rows"]) == {"robust_dr", "learned", "learned_context", "bayes", "glfs",
                                  "pixel_context", "family_table", "family_moments", "family",
                                  "family_rd", "read_map",
                                  "read_map_spatial"}
  assert all(r["ms_per_frame"] > 0 for r in results["rows"].values())
  assert {(p["rule"], p["peer"]) for p in results["pairs"]} >= set(context_bench.PAIRS)
  assert "| learned_context |" in context_bench.to_markdown(results)


def test_the_soak_with_free_space_clearing_on_finds_no_violation():
  # A few calls of bench/fuzz.py through fuse_frame and fuse_sequence, clearing on: voxels are
  # freed and restarted (frames look again from earlier poses), and every check of a cleared
  # map holds (fuse_batch with clearing: tests/library/test_batch.py).
  from bench import fuzz  # pylint: disable=import-outside-toplevel
  soak = fuzz.Soak(0)
  rng = np.random.default_rng(5)
  for entry, shape, calls in (("frame", fuzz.FRAME_SHAPES[0], 12),
                              ("sequence", fuzz.SEQUENCE_SHAPES[0], 2)):
    for _ in range(calls):
      soak.call(entry, shape, "bayes", rng, free_space=True)
  assert not soak.violations, soak.examples
  assert soak.counts["maps_checked_free_space"] >= 10
  assert soak.counts["free_voxels_at_checks"] > 0 and soak.counts["restarted_voxels"] > 0
