"""Ground truth for a researcher's own data: streamed label-image GT (bit-identical to the
whole-sequence GT of before), a hand-computed vote, a slow NumPy reference, and GT from a
labelled mesh (docs/equations.md §7.1–§7.3)."""

import collections
import dataclasses

import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxfusion
from jaxfusion import fusion, readout, rules, state as state_lib
from jaxfusion import datasets
from jaxfusion.datasets import classes
from jaxfusion.datasets import plyfile
from jaxfusion.datasets import ground_truth as gt_lib
from jaxfusion.datasets.classes import IGNORE_LABEL

KEYS = ("coords", "labels", "hits")


def old_gt_voxel_labels(sequence, *, voxel_size=0.1):
  """The implementation of `gt_voxel_labels` before streaming (kept here as the reference
  the study's numbers came from): a NumPy count sizes a fixed map, one `fuse_frame` per
  frame."""
  num_classes = sequence.num_classes
  capacity = state_lib.capacity_for(gt_lib.count_voxels(sequence, voxel_size=voxel_size),
                                    load=0.5)
  rule = rules.sum_labels()
  state = state_lib.init_map(capacity=capacity, num_classes=num_classes, voxel_size=voxel_size,
                             rule=rule)
  for frame in sequence:
    labels = jnp.asarray(frame.labels, jnp.int32)
    ok = (labels >= 0) & (labels < num_classes)
    depth = jnp.where(ok, jnp.asarray(frame.depth, jnp.float32), 0.0)
    probs = jax.nn.one_hot(jnp.where(ok, labels, 0), num_classes, dtype=jnp.float32)
    state = fusion.fuse_frame(state, fusion.Frame(depth, frame.T_world_cam, probs),
                              sequence.camera, rule)
  out = readout.read_map(state)
  return {k: out[k] for k in KEYS}


def assert_same(got, want):
  for k in KEYS:
    assert got[k].dtype == want[k].dtype == np.int32, k
    np.testing.assert_array_equal(got[k], want[k], err_msg=k)


@pytest.fixture(scope="module")
def office():
  """The tiny embedded sequence, with some ignored and some out-of-range labels."""
  seq = datasets.make_sequence("office", 0, num_frames=4, height=24, width=32, seed=1)
  labels = seq.labels.copy()
  labels[:, :3] = IGNORE_LABEL
  labels[1, -2:] = seq.num_classes          # outside the label space: never votes
  seq = dataclasses.replace(seq, labels=labels)
  return seq, old_gt_voxel_labels(seq)


@pytest.mark.parametrize("chunk", [1, 2, 4])
def test_streamed_gt_is_bit_identical_to_the_whole_sequence_gt(office, chunk):
  seq, want = office
  chunks = (seq.subset(range(s, min(s + chunk, len(seq)))) for s in range(0, len(seq), chunk))
  got = gt_lib.gt_from_frames(chunks, camera=seq.camera, num_classes=seq.num_classes,
                              voxel_size=0.1)
  assert_same(got, want)
  assert len(want["coords"]) > 100
  assert_same(datasets.gt_voxel_labels(seq, voxel_size=0.1, chunk=chunk), want)


@pytest.mark.slow
def test_streamed_gt_of_single_frames_into_a_map_that_grows(office, monkeypatch):
  seq, want = office
  # One `RGBDFrame` at a time, into a map that starts too small and grows.
  monkeypatch.setattr(gt_lib, "INITIAL_CAPACITY", 1024)
  assert len(want["coords"]) > 0.5 * 1024
  got = gt_lib.gt_from_frames(iter(seq), camera=seq.camera, num_classes=seq.num_classes)
  assert_same(got, want)


def test_streamed_gt_of_dicts_into_a_fixed_map_and_by_default(office):
  seq, want = office
  assert_same(datasets.gt_voxel_labels(seq), want)                      # default chunking
  # `stacked()` dicts into a fixed map.
  got = gt_lib.gt_from_frames([seq.subset([0, 1]).stacked(), seq.subset([2, 3]).stacked()],
                              camera=seq.camera, num_classes=seq.num_classes, capacity=2**13)
  assert_same(got, want)


def test_chunks_without_labels_or_of_bad_shapes_are_refused(office):
  seq, _ = office
  with pytest.raises(ValueError, match="no ground-truth labels"):
    gt_lib.gt_from_frames([{"depth": seq.depth, "T_world_cam": seq.T_world_cam}],
                          camera=seq.camera, num_classes=seq.num_classes)
  with pytest.raises(ValueError, match="labels"):
    gt_lib.gt_from_frames([{"depth": seq.depth, "T_world_cam": seq.T_world_cam,
                            "labels": seq.labels[:2]}], camera=seq.camera, num_classes=7)


# A camera whose pixel (u, v) at depth 1.05 m lands at x = 0.105·(u + 0.5), y = 0.105·(v + 0.5):
# with 0.2 m voxels every 2×2 block of pixels is one voxel, ≥ 0.05 m from its faces.
CAMERA = jaxfusion.Camera(10.0, 10.0, -0.5, -0.5)
DEPTH = 1.05
VOXEL = 0.2


def tiny_sequence(labels, depth, shifts):
  """A sequence of `(T, H, W)` labels and depth, camera translated by `shifts (T, 3)` voxels."""
  labels = np.asarray(labels, np.int32)
  t, h, w = labels.shape
  poses = np.tile(np.eye(4, dtype=np.float32), (t, 1, 1))
  poses[:, :3, 3] = VOXEL * np.asarray(shifts, np.float32)
  return datasets.RGBDSequence("tiny", ("a", "b", "c"), CAMERA, np.zeros((t, h, w, 3), np.uint8),
                               np.asarray(depth, np.float32), poses, labels)


def test_a_hand_computed_vote():
  labels = [[[0, 0, 2, 2],           # frame 0, at the origin
             [1, -1, 0, 0],
             [2, 2, 1, 1],
             [2, 2, 1, 0]],
            [[1, 1, -1, -1],         # frame 1, at the origin: 3 is no class, row 2 left has
             [2, 3, -1, -1],         # no depth
             [0, 0, 1, 1],
             [0, 0, 0, 0]],
            [[2, 0, 1, 1],           # frame 2, one voxel further along x
             [-1, -1, 1, 1],
             [-1, -1, -1, -1],
             [-1, -1, -1, -1]]]
  depth = np.full((3, 4, 4), DEPTH)
  depth[1, 2, :2] = 0.0
  seq = tiny_sequence(labels, depth, [[0, 0, 0], [0, 0, 0], [1, 0, 0]])
  # (0,0): {0: 2, 1: 1} + {1: 2, 2: 1} → 1 | (0,1): {2: 4} + {0: 2} → 2
  # (1,0): {0: 2, 2: 2} + {2: 1, 0: 1} → tie 3:3 → 0 | (1,1): {1: 3, 0: 1} + {1: 2, 0: 2} → 1
  # (2,0): {1: 4} → 1
  want = {"coords": np.array([[0, 0, 5], [0, 1, 5], [1, 0, 5], [1, 1, 5], [2, 0, 5]], np.int32),
          "labels": np.array([1, 2, 0, 1, 1], np.int32),
          "hits": np.array([6, 6, 6, 8, 4], np.int32)}
  assert_same(datasets.gt_voxel_labels(seq, voxel_size=VOXEL), want)
  assert_same(gt_lib.gt_from_frames(iter(seq), camera=CAMERA, num_classes=3, voxel_size=VOXEL),
              want)


def numpy_majority(seq):
  """Slow reference: a dict of voxels counting labels (float64 keys), ties to the lowest."""
  votes = collections.defaultdict(lambda: np.zeros(seq.num_classes, np.int64))
  for f in seq:
    for v, u in zip(*np.nonzero(f.depth > 0)):
      y = int(f.labels[v, u])
      if not 0 <= y < seq.num_classes:
        continue
      d = float(f.depth[v, u])
      p = np.array([d * (u - CAMERA.cx) / CAMERA.fx, d * (v - CAMERA.cy) / CAMERA.fy, d])
      T = f.T_world_cam.astype(np.float64)
      key = tuple(int(k) for k in np.floor((T[:3, :3] @ p + T[:3, 3]) / VOXEL))
      votes[key][y] += 1
  keys = sorted(votes)
  return {"coords": np.array(keys, np.int32).reshape(-1, 3),
          "labels": np.array([np.argmax(votes[k]) for k in keys], np.int32),
          "hits": np.array([votes[k].sum() for k in keys], np.int32)}


@hypothesis.settings(max_examples=8, deadline=None)
@hypothesis.given(
    labels=st.lists(st.integers(-1, 3), min_size=3 * 4 * 6, max_size=3 * 4 * 6),
    holes=st.lists(st.booleans(), min_size=3 * 4 * 6, max_size=3 * 4 * 6),
    shifts=st.lists(st.integers(-1, 1), min_size=9, max_size=9))
def test_against_a_numpy_majority_vote(labels, holes, shifts):
  depth = np.where(np.reshape(holes, (3, 4, 6)), 0.0, DEPTH)
  seq = tiny_sequence(np.reshape(labels, (3, 4, 6)), depth, np.reshape(shifts, (3, 3)))
  assert_same(datasets.gt_voxel_labels(seq, voxel_size=VOXEL), numpy_majority(seq))


# ---- Labelled meshes -----------------------------------------------------------------------

SCANNET12 = classes.label_space("scannet12")[1]
NYU40 = classes.label_space("nyu40")[1]
CHAIR, SOFA, WALL = 5, 6, 1                       # NYU40 ids
CHAIR12 = classes.SCANNET_CLASS_NAMES.index("chair")
SOFA12 = classes.SCANNET_CLASS_NAMES.index("sofa")


def quad(x0, x1, y0, y1, z, ids):
  """Two triangles over `[x0, x1] × [y0, y1]` at height z; `ids`: the 4 corners' labels."""
  v = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float64)
  return v, np.array([[0, 1, 2], [0, 2, 3]]), np.asarray(ids)


def box(lo, hi, label):
  """The 12 triangles of an axis-aligned box, every corner labelled `label`."""
  corners = np.array([[x, y, z] for z in (lo, hi) for y in (lo, hi) for x in (lo, hi)],
                     np.float64)
  quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
  faces = [tri for a, b, c, d in quads for tri in ((a, b, c), (a, c, d))]
  return corners, np.array(faces), np.full(8, label)


def grid(*ranges):
  return np.array([[i, j, k] for i in ranges[0] for j in ranges[1] for k in ranges[2]], np.int32)


def test_a_labelled_quad_and_box_give_the_voxels_of_their_surface():
  gt = gt_lib.gt_from_mesh(*quad(0.01, 0.29, 0.01, 0.29, 0.25, [CHAIR] * 4), lut=SCANNET12,
                           voxel_size=0.1)
  np.testing.assert_array_equal(gt["coords"], grid(range(3), range(3), [2]))
  assert np.all(gt["labels"] == CHAIR12) and np.all(gt["hits"] > 0)
  assert all(gt[k].dtype == np.int32 for k in KEYS)
  gt = gt_lib.gt_from_mesh(*box(0.02, 0.18, SOFA), lut=SCANNET12, voxel_size=0.1)
  np.testing.assert_array_equal(gt["coords"], grid(range(2), range(2), range(2)))
  assert np.all(gt["labels"] == SOFA12)
  # The default spacing is a quarter voxel: a 0.16 m face holds ≥ (0.16 / 0.025)² samples.
  assert gt["hits"].sum() >= 6 * (0.16 / 0.025)**2


@pytest.mark.parametrize("first,second", [(CHAIR, SOFA), (SOFA, CHAIR)])
def test_two_touching_faces_tie_to_the_lowest_class(first, second):
  # Two mirror-image triangles in one voxel, each with its own corners (so its own label):
  # the same number of samples each, a tie, won by chair (class 2) over sofa (class 7).
  v = np.array([[0.01, 0.01, 0.05], [0.09, 0.01, 0.05], [0.09, 0.09, 0.05],
                [0.01, 0.01, 0.05], [0.09, 0.09, 0.05], [0.01, 0.09, 0.05]])
  labels = np.array([first] * 3 + [second] * 3)
  gt = gt_lib.gt_from_mesh(v, [[0, 1, 2], [3, 4, 5]], labels, lut=SCANNET12, voxel_size=0.1)
  np.testing.assert_array_equal(gt["coords"], [[0, 0, 0]])
  assert gt["labels"][0] == CHAIR12 and gt["hits"][0] % 2 == 0
  # A third, smaller face of sofa in the same voxel breaks the tie.
  v3 = np.concatenate([v, [[0.02, 0.05, 0.07], [0.03, 0.05, 0.07], [0.03, 0.06, 0.07]]])
  gt3 = gt_lib.gt_from_mesh(v3, [[0, 1, 2], [3, 4, 5], [6, 7, 8]],
                            np.concatenate([labels, [SOFA] * 3]), lut=SCANNET12, voxel_size=0.1)
  assert gt3["labels"][0] == SOFA12 and gt3["hits"][0] > gt["hits"][0]


def test_samples_take_the_label_of_the_nearest_corner():
  v = np.array([[0.01, 0.01, 0.05], [0.39, 0.01, 0.05], [0.01, 0.39, 0.05]])
  gt = gt_lib.gt_from_mesh(v, [[0, 1, 2]], np.array([CHAIR, SOFA, SOFA]), lut=SCANNET12,
                           voxel_size=0.1)
  label = {tuple(c): l for c, l in zip(gt["coords"], gt["labels"])}
  assert label[(0, 0, 0)] == CHAIR12
  assert label[(3, 0, 0)] == SOFA12 and label[(0, 3, 0)] == SOFA12


def test_labels_outside_the_label_space_are_dropped():
  wall = quad(0.01, 0.19, 0.01, 0.19, 0.05, [WALL, WALL, 0, 300])  # wall, unannotated, no id
  chair = quad(0.51, 0.59, 0.01, 0.09, 0.05, [CHAIR] * 4)
  v = np.concatenate([wall[0], chair[0]])
  f = np.concatenate([wall[1], chair[1] + 4])
  labels = np.concatenate([wall[2], chair[2]])
  gt = gt_lib.gt_from_mesh(v, f, labels, lut=SCANNET12, voxel_size=0.1)
  np.testing.assert_array_equal(gt["coords"], [[5, 0, 0]])
  np.testing.assert_array_equal(gt["labels"], [CHAIR12])
  # In NYU40's own space the wall is class 0; the unannotated and unknown ids still drop.
  gt = gt_lib.gt_from_mesh(v, f, labels, lut=NYU40, voxel_size=0.1)
  label = {tuple(c): l for c, l in zip(gt["coords"], gt["labels"])}
  assert label.pop((5, 0, 0)) == CHAIR - 1
  assert {(0, 0, 0), (1, 0, 0)} <= set(label) <= {(0, 0, 0), (0, 1, 0), (1, 0, 0), (1, 1, 0)}
  assert set(label.values()) == {WALL - 1}
  nothing = gt_lib.gt_from_mesh(*quad(0, 1, 0, 1, 0, [0, 0, WALL, 255]), lut=SCANNET12)
  assert nothing["coords"].shape == (0, 3) and nothing["labels"].dtype == np.int32


def test_surface_from_mesh_points_lie_on_the_mesh_one_per_cell():
  spacing = 0.02
  s = gt_lib.surface_from_mesh(*quad(0.01, 0.29, 0.01, 0.29, 0.25, [CHAIR, CHAIR, WALL, WALL]),
                               lut=SCANNET12, spacing=spacing)
  p = s["points"]
  assert p.dtype == np.float64 and s["labels"].dtype == np.int32 and len(p) == len(s["labels"])
  np.testing.assert_allclose(p[:, 2], 0.25)
  assert np.all((p[:, :2] >= 0.01 - 1e-12) & (p[:, :2] <= 0.29 + 1e-12))
  cells = np.floor(p / spacing).astype(int)
  assert len(np.unique(cells, axis=0)) == len(p)                   # one point per cell
  inner = {(i, j) for i in range(1, 14) for j in range(1, 14)}      # cells inside the square
  assert inner <= set(map(tuple, cells[:, :2]))
  # Wall corners keep their geometry with IGNORE_LABEL; chair corners label theirs.
  assert set(s["labels"]) == {CHAIR12, IGNORE_LABEL}


def test_gt_from_a_labelled_mesh_file(tmp_path):
  v, f, labels = box(0.02, 0.18, SOFA)
  path = plyfile.write_labelled_mesh(str(tmp_path / "scene_vh_clean_2.labels.ply"),
                                     {"vertices": v, "faces": f, "labels": labels})
  mesh = plyfile.read_labelled_mesh(path)
  got = gt_lib.gt_from_mesh(mesh["vertices"], mesh["faces"], mesh["labels"], lut=SCANNET12)
  want = gt_lib.gt_from_mesh(v, f, labels, lut=SCANNET12)
  np.testing.assert_array_equal(got["coords"], want["coords"])
  np.testing.assert_array_equal(got["labels"], want["labels"])


def test_bad_meshes_are_refused():
  v, f, labels = quad(0, 1, 0, 1, 0, [CHAIR] * 4)
  with pytest.raises(ValueError, match="faces index"):
    gt_lib.gt_from_mesh(v, f + 2, labels, lut=SCANNET12)
  with pytest.raises(ValueError, match="one per vertex"):
    gt_lib.gt_from_mesh(v, f, labels[:3], lut=SCANNET12)
  with pytest.raises(ValueError, match="spacing"):
    gt_lib.surface_from_mesh(v, f, labels, lut=SCANNET12, spacing=0.0)
  with pytest.raises(ValueError, match="vertices"):
    gt_lib.gt_from_mesh(np.full((4, 3), np.nan), f, labels, lut=SCANNET12)
