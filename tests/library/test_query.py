"""`query` (what the map holds at world points) and `read_map(classes=..., box=...)`, both
against the full `read_map` on random maps, and the README's information-gain example."""

import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra import numpy as hnp

import jaxfusion as jf
from jaxfusion import camera as camera_lib
from jaxfusion import hashing
from jaxfusion import readout
from tests import engine_helpers as h

ROOT = pathlib.Path(__file__).resolve().parents[2]
RULES = ("sum_probs", "bayes", "robust_dr")   # one per posterior kind: S/ΣS, softmax, Dirichlet
HEIGHT, WIDTH, K = 8, 10, h.NUM_CLASSES
CAM = jf.Camera(6.0, 6.0, 4.5, 3.5)
SIZE = 0.25
CAPACITY = 2**12
PADDED = 1024   # points per query in the tests of one rule (one compilation per rule)


@pytest.fixture(autouse=True)
def strict_rank_promotion():
  with jax.numpy_rank_promotion("raise"):
    yield


def origin_frame(rng):
  """A frame whose pixels land around (0.1, 0.1, 0.1) m, so the map holds voxel (0, 0, 0):
  the key an invalid point is given before it is masked out."""
  T = np.eye(4, dtype=np.float32)
  T[:3, 3] = [0.1, 0.1, -0.4]
  frame = h.random_frame(rng, height=HEIGHT, width=WIDTH, camera=CAM, T=T)
  depth = h.drop_ambiguous_pixels(np.full((HEIGHT, WIDTH), 0.5, np.float32), T, CAM, SIZE)
  return frame._replace(depth=depth)


def random_frames(seed, num_frames):
  rng = np.random.default_rng(seed)
  return [origin_frame(rng)] + [
      h.random_frame(rng, height=HEIGHT, width=WIDTH, camera=CAM) for _ in range(num_frames)]


def build_map(name, *, seed=0, num_frames=3, **hparams):
  rule = jf.rules.by_name(name, **h.rule_kwargs(name, **hparams))
  state = jf.init_map(capacity=CAPACITY, num_classes=K, voxel_size=SIZE, rule=rule)
  for frame in random_frames(seed, num_frames):
    state = jf.fuse_frame(state, frame, CAM, rule)
  return state


@pytest.fixture(scope="module")
def maps():
  return {name: build_map(name) for name in RULES}


@pytest.fixture(scope="module")
def voxels(maps):
  return {name: jf.read_map(state) for name, state in maps.items()}


def ask(state, points):
  """`jf.query` on `(..., 3)` points padded with NaN to PADDED points, so that the tests of one
  rule compile one query; the answer for the given points, with their leading shape."""
  points = np.asarray(points, np.float32)
  flat = points.reshape(-1, 3)
  assert len(flat) <= PADDED
  padded = np.full((PADDED, 3), np.nan, np.float32)
  padded[:len(flat)] = flat
  q = jf.query(state, padded)
  assert isinstance(q, jf.QueryResult)
  assert q.found.dtype == bool and q.posterior.dtype == q.entropy.dtype == jnp.float32
  assert q.hits.dtype == jnp.int32 and q.posterior.shape == (PADDED, state.num_classes)
  return jf.QueryResult(*(np.asarray(x)[:len(flat)].reshape(points.shape[:-1] + x.shape[1:])
                          for x in q))


def prior_entropy():
  return np.float32(math.log(K))


# --- query against read_map --------------------------------------------------------------------
@pytest.mark.parametrize("name", RULES)
def test_query_at_voxel_centres_equals_read_map(maps, voxels, name):
  state, voxels = maps[name], voxels[name]
  assert len(voxels["coords"]) > 20
  assert any((voxels["coords"] == 0).all(axis=1))           # voxel (0, 0, 0) is in the map
  q = ask(state, voxels["centers"])
  assert q.found.all()
  np.testing.assert_allclose(q.posterior, voxels["posterior"], rtol=1e-6, atol=1e-7)
  np.testing.assert_allclose(q.entropy, voxels["entropy"], rtol=1e-5, atol=1e-6)
  np.testing.assert_array_equal(q.hits, voxels["hits"])
  np.testing.assert_array_equal(np.argmax(q.posterior, axis=-1), voxels["labels"])


@pytest.mark.parametrize("name", RULES)
def test_any_point_inside_a_voxel_gets_that_voxels_answer(maps, voxels, name):
  state, voxels = maps[name], voxels[name]
  rng = np.random.default_rng(1)
  offsets = rng.uniform(0.01, 0.99, (4,) + voxels["coords"].shape)    # 4 points per voxel
  points = ((voxels["coords"] + offsets) * SIZE).astype(np.float32)
  q = ask(state, points)
  assert q.found.all()
  np.testing.assert_array_equal(q.posterior, np.broadcast_to(q.posterior[0], q.posterior.shape))
  np.testing.assert_allclose(q.posterior[0], voxels["posterior"], rtol=1e-6, atol=1e-7)
  np.testing.assert_array_equal(q.hits, np.broadcast_to(voxels["hits"], q.hits.shape))


def test_every_fused_pixels_point_finds_its_voxel(maps):
  # The world point of every valid pixel, back-projected here, is in the voxel fuse_frame put
  # it in (random_frame makes holes of the pixels within 1e-3 voxels of a face).
  state, total = maps["bayes"], 0
  for frame in random_frames(0, 3):
    valid = np.isfinite(frame.depth) & (frame.depth > 0)
    p_world = camera_lib.transform_points(frame.T_world_cam,
                                          camera_lib.backproject(frame.depth, CAM))
    q = ask(state, np.asarray(p_world)[valid])
    assert q.found.all() and (q.hits > 0).all()
    total += int(valid.sum())
  assert total > 100


@pytest.mark.parametrize("name", RULES)
def test_points_outside_every_voxel_report_the_prior(maps, voxels, name):
  state, coords = maps[name], voxels[name]["coords"]
  far = np.array([[400, 0, 0], [-3, 1000, 7], [0, 0, -(2**20)], [12345, -54321, 999]])
  assert not (coords[:, None] == far[None]).all(-1).any()
  # Also the voxels next to stored ones that are not stored themselves.
  neighbours = (coords[:, None] + np.eye(3, dtype=np.int32)[None]).reshape(-1, 3)
  stored = {tuple(c) for c in coords}
  neighbours = np.array([c for c in neighbours if tuple(c) not in stored])
  points = ((np.concatenate([far, neighbours]) + 0.5) * SIZE).astype(np.float32)
  q = ask(state, points)
  assert not q.found.any()
  np.testing.assert_allclose(q.posterior, 1.0 / K, rtol=1e-6)     # the prior of the six rules
  np.testing.assert_allclose(q.entropy, prior_entropy(), rtol=1e-6)
  assert not q.hits.any()


@pytest.mark.parametrize("name", RULES)
def test_non_finite_and_out_of_range_points_are_not_found(maps, name):
  state = maps[name]
  inf, nan, big = np.inf, np.nan, 2.0**30 * SIZE * 2
  # Every one of these would get key (0, 0, 0) if it were not masked — and that voxel is stored.
  points = np.array([[nan, 0.1, 0.1], [0.1, inf, 0.1], [0.1, 0.1, -inf], [nan, nan, nan],
                     [big, 0.1, 0.1], [0.1, -big, 0.1], [1e38, 1e38, 1e38],
                     [0.1, 0.1, 0.1]], np.float32)
  q = ask(state, points)
  np.testing.assert_array_equal(q.found, [False] * 7 + [True])
  for leaf in q:
    assert np.isfinite(leaf).all()
  np.testing.assert_allclose(q.entropy[:7], prior_entropy(), rtol=1e-6)
  assert not q.hits[:7].any()


# --- shapes, transformations -------------------------------------------------------------------
def test_any_leading_shape_and_vmap_over_points(maps, voxels):
  state = maps["robust_dr"]
  centers = voxels["robust_dr"]["centers"][:12]
  points = np.concatenate([centers, np.full((12, 3), 50.0, np.float32)]).reshape(2, 3, 4, 3)
  q = jf.query(state, points)
  assert q.found.shape == q.entropy.shape == q.hits.shape == (2, 3, 4)
  assert q.posterior.shape == (2, 3, 4, K)
  flat = ask(state, points.reshape(-1, 3))
  np.testing.assert_array_equal(flat.found, [True] * 12 + [False] * 12)
  for a, b in zip(q, flat):
    np.testing.assert_allclose(np.asarray(a).reshape(np.shape(b)), b, rtol=1e-6, atol=1e-7)
  one = jf.query(state, points[0, 0, 0])                      # a single point: shape ()
  assert one.found.shape == () and one.posterior.shape == (K,) and bool(one.found)
  none = jf.query(state, np.zeros((0, 3), np.float32))
  assert none.found.shape == (0,) and none.posterior.shape == (0, K)
  mapped = jax.vmap(jf.query, in_axes=(None, 0))(state, points.reshape(-1, 3))
  for a, b in zip(mapped, flat):
    np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-7)
  # A Python list of float64 numbers is points too (computed in float32, as the engine does).
  listed = jf.query(state, points.astype(np.float64).tolist())
  for a, b in zip(listed, q):
    np.testing.assert_array_equal(a, b)


def test_under_jit_one_compilation_for_maps_of_the_same_shape(maps, voxels):
  traces = []

  @jax.jit
  def gain(state, points):
    traces.append(1)
    return jf.query(state, points).entropy.mean()

  first = maps["robust_dr"]
  second = build_map("robust_dr", seed=5, num_frames=1, beta=0.6, alpha0=2.0)
  points = np.full((PADDED, 3), np.nan, np.float32)
  centers = voxels["robust_dr"]["centers"][:PADDED]
  points[:len(centers)] = centers
  values = [float(gain(first, points)), float(gain(second, points))]
  assert len(traces) == 1 and values[0] != values[1]
  np.testing.assert_allclose(values[1], np.mean(ask(second, points).entropy), rtol=1e-6)
  # The eager entry point is jitted itself and does not recompile either.
  before = readout._query_jit._cache_size()
  ask(first, points)
  ask(second, points + np.float32(0.01))
  assert readout._query_jit._cache_size() == before


def test_vmap_over_candidate_poses_and_a_batch_of_maps(maps, voxels):
  state = maps["bayes"]
  depth = np.full((HEIGHT, WIDTH), 1.0, np.float32)
  p_cam = camera_lib.backproject(depth, CAM)
  poses = np.stack([h.pose(np.random.default_rng(i)) for i in range(3)])

  def view_entropy(T):
    return jf.query(state, camera_lib.transform_points(T, p_cam)).entropy.mean()

  one_by_one = [ask(state, camera_lib.transform_points(T, p_cam)).entropy.mean() for T in poses]
  np.testing.assert_allclose(jax.jit(jax.vmap(view_entropy))(poses), one_by_one, rtol=1e-6)
  batched = jax.tree.map(lambda a, b: jnp.stack([a, b]), state, maps["bayes"])
  points = voxels["bayes"]["centers"][:8]
  q = jax.vmap(jf.query, in_axes=(0, None))(batched, points)
  assert q.found.shape == (2, 8) and bool(q.found.all())


def test_gradients_flow_to_the_rows_of_the_found_voxels(maps, voxels):
  state = maps["robust_dr"]
  points = voxels["robust_dr"]["centers"][:10]

  def loss(rows):
    return jf.query(state.replace(rows=rows), points).entropy.sum()

  grads = jax.grad(loss)(state.rows)
  slots, _ = hashing.lookup(state.keys, jnp.floor(points / SIZE).astype(jnp.int32),
                               max_probes=state.max_probes)
  for g in jax.tree.leaves(grads):
    assert bool(jnp.all(jnp.isfinite(g)))
  touched = np.zeros(state.capacity, bool)
  touched[np.asarray(slots)] = True
  g = np.asarray(grads["logp"])
  assert np.abs(g[touched]).sum() > 0 and not np.abs(g[~touched]).any()


# --- the prior of unobserved voxels -----------------------------------------------------------
def test_unobserved_voxels_report_a_custom_rules_prior_and_a_full_map_uniform():
  p0 = np.array([0.7, 0.1, 0.1, 0.1], np.float32)
  rule = jf.rules.bayes().replace(init=lambda k, hp: {"logp": jnp.log(jnp.asarray(p0))})
  state = jf.init_map(capacity=16, num_classes=K, voxel_size=SIZE, rule=rule)
  q = jf.query(state, np.zeros((2, 3), np.float32))
  np.testing.assert_allclose(q.posterior, np.broadcast_to(p0, (2, K)), rtol=1e-6)
  np.testing.assert_allclose(q.entropy, -np.sum(p0 * np.log(p0)), rtol=1e-5)
  # A map with no empty slot has no prior row left to read: uniform.
  keys = np.stack([np.arange(16), np.zeros(16), np.zeros(16)], -1).astype(np.int32)
  full = state.replace(keys=jnp.asarray(keys), hits=jnp.ones(16, jnp.int32),
                       num_occupied=jnp.asarray(16, jnp.int32))
  q = jf.query(full, np.array([[0.1, 0.1, 0.1], [-5.0, 0.0, 0.0]], np.float32))
  np.testing.assert_array_equal(q.found, [True, False])
  np.testing.assert_allclose(q.posterior[1], 1.0 / K, rtol=1e-6)


# --- read_map(classes=..., box=...) ------------------------------------------------------------
def numpy_filter(voxels, classes=None, box=None):
  keep = np.ones(len(voxels["coords"]), bool)
  if classes is not None:
    keep &= np.isin(voxels["labels"], classes)
  if box is not None:
    c = voxels["centers"].astype(np.float64)
    keep &= np.all((c >= np.asarray(box[0])) & (c <= np.asarray(box[1])), axis=1)
  return {name: value[keep] for name, value in voxels.items()}


def assert_same_voxels(got, want):
  assert sorted(got) == sorted(want)
  for name in want:
    assert got[name].dtype == want[name].dtype, name
    np.testing.assert_array_equal(got[name], want[name], err_msg=name)


@pytest.mark.parametrize("name", RULES)
def test_read_map_by_classes_and_box_equals_filtering_the_full_map(maps, voxels, name):
  state, full = maps[name], voxels[name]
  assert_same_voxels(jf.read_map(state, classes=None, box=None), full)
  rng = np.random.default_rng(2)
  centers = full["centers"].astype(np.float64)
  for _ in range(6):
    classes = sorted(rng.choice(K, rng.integers(0, K + 1), replace=False).tolist())
    a, b = centers[rng.integers(len(centers), size=2)]
    box = (np.minimum(a, b), np.maximum(a, b))        # corners on voxel centres: faces included
    for kwargs in ({"classes": classes}, {"box": box}, {"classes": classes, "box": box}):
      assert_same_voxels(jf.read_map(state, **kwargs), numpy_filter(full, **kwargs))
  # A box shrunk to one voxel's centre keeps exactly that voxel; a box between centres none.
  one = jf.read_map(state, box=(centers[3], centers[3]))
  np.testing.assert_array_equal(one["coords"], full["coords"][3:4])
  assert len(jf.read_map(state, box=(centers[3] + 0.01, centers[3] + 0.2))["coords"]) == 0
  # A single index and NumPy integers work as well as a list.
  label = int(full["labels"][0])
  assert_same_voxels(jf.read_map(state, classes=np.int64(label)),
                     numpy_filter(full, classes=[label]))
  assert_same_voxels(jf.read_map(state, classes=np.arange(K)), full)


def test_read_map_with_classes_and_box_still_warns_when_voxels_were_dropped(maps):
  state = maps["bayes"].replace(num_dropped=jnp.asarray(3, jnp.int32))
  with pytest.warns(jf.MapFullWarning, match="3 voxel insertions were dropped"):
    jf.read_map(state, classes=[0], box=((-1, -1, -1), (1, 1, 1)))


# --- bad arguments -----------------------------------------------------------------------------
@pytest.mark.parametrize("kwargs,error,match", [
    ({"classes": [K]}, ValueError, "out of range"),
    ({"classes": [-1]}, ValueError, "out of range"),
    ({"classes": [0.5]}, TypeError, "integer class indices"),
    ({"classes": [True]}, TypeError, "integer class indices"),
    ({"classes": "wall"}, TypeError, "integer class indices"),
    ({"classes": 1.0}, TypeError, "sequence of class indices"),
    ({"box": ((0, 0), (1, 1))}, ValueError, "shape \\(3,\\)"),
    ({"box": ((0, 0, 0), (1, np.nan, 1))}, ValueError, "finite"),
    ({"box": ((0, 2, 0), (1, 1, 1))}, ValueError, "min must be ≤ max"),
    ({"box": (0, 0, 0)}, TypeError, "pair \\(min_xyz, max_xyz\\)"),
    ({"box": 1.0}, TypeError, "pair \\(min_xyz, max_xyz\\)"),
    ({"box": (("a", 0, 0), (1, 1, 1))}, TypeError, "pair \\(min_xyz, max_xyz\\)"),
])
def test_read_map_rejects_bad_classes_and_boxes(maps, kwargs, error, match):
  with pytest.raises(error, match=match):
    jf.read_map(maps["bayes"], **kwargs)


def test_query_rejects_bad_arguments(maps):
  state = maps["bayes"]
  point = np.zeros((1, 3), np.float32)
  with pytest.raises(TypeError, match="MapState"):
    jf.query({"keys": state.keys}, point)
  batched = jax.tree.map(lambda a: jnp.stack([a, a]), state)
  with pytest.raises(ValueError, match="one map.*vmap"):
    jf.query(batched, point)
  with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
    jf.query(state, np.zeros((4, 2), np.float32))
  with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
    jf.query(state, np.float32(1.0))
  with pytest.raises(TypeError, match="float array"):
    jf.query(state, np.zeros((4, 3), np.int32))
  with pytest.raises(TypeError, match="float array"):
    jf.query(state, [[0, 0, 0]])
  with pytest.raises(TypeError, match="float array"):
    jf.query(state, [[0.0, 0.0], [0.0]])
  with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):        # checked under jit too
    jax.jit(jf.query)(state, jnp.zeros((4, 2)))


# --- property ----------------------------------------------------------------------------------
@settings(max_examples=50, deadline=None)
@given(picks=hnp.arrays(np.int64, 16, elements=st.integers(0, 10**6)),
       offsets=hnp.arrays(np.float32, (16, 3), elements=st.floats(-1.5, 1.5, width=32)),
       holes=hnp.arrays(bool, 16))
def test_found_iff_the_points_voxel_is_stored(maps, voxels, picks, offsets, holes):
  state, voxels = maps["sum_probs"], voxels["sum_probs"]
  # Points within ±1.5 voxels of stored voxel centres: about half land in a stored voxel.
  points = voxels["centers"][picks % len(voxels["centers"])] + offsets * np.float32(SIZE)
  points[holes, 1] = np.nan
  q = ask(state, points)
  with np.errstate(invalid="ignore"):
    keys = np.floor(points / np.float32(SIZE))
  stored = {tuple(c) for c in voxels["coords"]}
  expected = [bool(np.isfinite(k).all()) and tuple(k.astype(np.int32)) in stored for k in keys]
  np.testing.assert_array_equal(q.found, expected)
  index = {tuple(c): i for i, c in enumerate(voxels["coords"])}
  for i in np.nonzero(expected)[0]:
    j = index[tuple(keys[i].astype(np.int32))]
    np.testing.assert_allclose(q.posterior[i], voxels["posterior"][j], rtol=1e-6, atol=1e-7)
    assert int(q.hits[i]) == voxels["hits"][j]


# --- README ------------------------------------------------------------------------------------
def _python_block(text, heading):
  start = text.index("```python\n", text.index(heading)) + len("```python\n")
  return text[start:text.index("```", start)]


@pytest.mark.slow
def test_the_information_gain_example_runs_on_the_readme_quick_start_map(tmp_path,
                                                                           monkeypatch):
  monkeypatch.chdir(tmp_path)   # the quick start writes its mesh to the working folder
  text = (ROOT / "README.md").read_text(encoding="utf-8")
  queries = (ROOT / "docs" / "your_data.md").read_text(encoding="utf-8")
  scope = {}
  exec(_python_block(text, "## Quick start"), scope)     # pylint: disable=exec-used
  exec(_python_block(queries, "## Queries"), scope)      # pylint: disable=exec-used
  assert (tmp_path / "wall.ply").stat().st_size > 0
  state, gain = scope["state"], scope["gain"]
  q = jf.query(state, scope["p_world"])
  seen = float(q.found.mean())
  assert 0.2 < seen < 1.0                                # the shifted view sees some new space
  assert 0.0 <= gain <= math.log(state.num_classes) + 1e-6
  np.testing.assert_allclose(gain, float(q.entropy.mean()), rtol=1e-6)


def test_voxel_posteriors_called_plainly_runs_one_compiled_program():
  # voxel_posteriors reads every slot's (K,) row: called plainly it must run as one compiled
  # program per map (a (C, K) softmax op by op cost 2-3x), equal to the call under jax.jit.
  rule = jf.rules.robust()
  state = jf.init_map(capacity=2**8, num_classes=3, rule=rule)
  depth = np.full((6, 8), 2.0, np.float32)
  probs = np.random.default_rng(0).dirichlet(np.ones(3), (6, 8)).astype(np.float32)
  frame = jf.Frame(depth, np.eye(4, dtype=np.float32), probs, 0.01 * probs)
  state = jf.fuse_frame(state, frame, jf.Camera(8.0, 8.0, 3.5, 2.5), rule)
  before = readout._voxel_posteriors._cache_size()  # pylint: disable=protected-access
  post, occupied = jf.voxel_posteriors(state)
  jf.voxel_posteriors(state)
  assert readout._voxel_posteriors._cache_size() == before + 1  # pylint: disable=protected-access
  jit_post, jit_occupied = jax.jit(jf.voxel_posteriors)(state)
  np.testing.assert_array_equal(np.asarray(post), np.asarray(jit_post))
  np.testing.assert_array_equal(np.asarray(occupied), np.asarray(jit_occupied))
  assert int(occupied.sum()) == int(state.num_occupied) > 0
  with pytest.raises(TypeError, match="MapState"):
    jf.voxel_posteriors(state.rows)


@settings(max_examples=100, deadline=None)
@given(coords=hnp.arrays(np.int32, st.tuples(st.integers(0, 60), st.just(3)),
                         elements=st.integers(-3, 3) | st.integers(-2**30 + 1, 2**30 - 1)),
       narrow=st.booleans())
def test_coordinate_order_is_the_lexsort_of_the_columns(coords, narrow):
  """read_map's order (one sort of a packed code) against `np.lexsort` by x, then y, then z,
  on distinct coordinates: clustered ones (the packed code) and ones spread over ±2^30 (the
  fallback when the code would not fit in 63 bits)."""
  if narrow:
    coords = coords % 7 - 3
  coords = np.unique(coords, axis=0)
  np.random.default_rng(len(coords)).shuffle(coords)
  expected = np.lexsort((coords[:, 2], coords[:, 1], coords[:, 0]))
  np.testing.assert_array_equal(readout.coordinate_order(coords), expected)
