"""Meshes of the geometry layer (jaxfusion.mesh): marching cubes on the hashed TSDF against the
dense NumPy reference (itself checked against skimage in test_mc_tables), watertightness, the
bench room's faces, semantics per vertex and class, export round trips, empty maps."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxfusion as jf
from bench import scene
from jaxfusion import hashing
from jaxfusion import mesh as mesh_lib
from jaxfusion import tsdf
from tests import engine_helpers as h
from tests import mc_reference


@pytest.fixture(autouse=True)
def strict_rank_promotion():
  """The engine broadcasts explicitly: users may run with jax_numpy_rank_promotion='raise'."""
  with jax.numpy_rank_promotion("raise"):
    yield


VOXEL = 0.05


def _layer_from_volume(volume, origin, *, voxel_size=VOXEL, weight=None, capacity=2**9):
  """A geometry layer whose voxels `origin + (i, j, k)` hold `volume[i, j, k]` (weight 1, or
  `weight`), every other voxel unobserved; blocks are inserted through the layer's own hash."""
  state = tsdf.init_tsdf(voxel_size=voxel_size, capacity=capacity)
  b = state.block_size
  index = np.stack(np.meshgrid(*[np.arange(n) for n in volume.shape], indexing="ij"), -1)
  index = index.reshape(-1, 3) + np.asarray(origin)
  block = np.floor_divide(index, b)
  local = index - block * b
  flat = local[:, 0] + b * (local[:, 1] + b * local[:, 2])
  keys, inverse = np.unique(block, axis=0, return_inverse=True)
  result = hashing.insert(state.block_keys, state.claims, keys.astype(np.int32),
                          np.ones(len(keys), bool), max_probes=state.max_probes)
  assert bool(np.all(result.found))
  table, slots = np.asarray(result.table), np.asarray(result.slots)
  sdf = np.zeros(state.sdf.shape, np.float32)
  w = np.zeros(state.weight.shape, np.float32)
  sdf[slots[inverse.reshape(-1)], flat] = volume.reshape(-1)
  w[slots[inverse.reshape(-1)], flat] = 1.0 if weight is None else weight.reshape(-1)
  return state.replace(block_keys=np.asarray(table), sdf=sdf, weight=w,
                       num_blocks=np.int32(len(keys)))


def _triangle_set(vertices, faces, decimals=4):
  """Triangles as a set of vertex-coordinate triples, each rotated to start at its smallest
  vertex (orientation kept)."""
  out = set()
  for f in faces:
    tri = [tuple(np.round(vertices[i], decimals)) for i in f]
    k = min(range(3), key=lambda i: tri[i])
    out.add(tuple(tri[k:] + tri[:k]))
  return out


def _same_triangles(v1, f1, v2, f2, tol=1e-5):
  """The two meshes have the same oriented triangles up to order: vertices matched by position
  (within `tol`), each triangle rotated to start at its smallest vertex index."""
  from scipy.spatial import cKDTree
  if len(v1) != len(v2) or len(f1) != len(f2):
    return False
  distance, match = cKDTree(np.asarray(v1, np.float64)).query(np.asarray(v2, np.float64))
  if distance.max(initial=0) > tol or len(set(match.tolist())) != len(v1):
    return False
  rotate = lambda t: tuple(t[t.index(min(t)):] + t[:t.index(min(t))])
  return ({rotate(list(t)) for t in np.asarray(f1).tolist()}
          == {rotate(list(t)) for t in match[np.asarray(f2)].tolist()})


def _blob(shape=(14, 13, 12), seed=0):
  rng = np.random.default_rng(seed)
  x = np.stack(np.meshgrid(*[np.arange(n, dtype=float) for n in shape], indexing="ij"), -1)
  field = np.full(shape, 2.0)
  for _ in range(3):
    c = rng.uniform(3, np.array(shape) - 3)
    field = np.minimum(field, (np.linalg.norm(x - c, axis=-1) - rng.uniform(2, 3.5)) * 0.3)
  return np.clip(field + 0.05 * rng.normal(size=shape), -0.2, 0.2).astype(np.float32)


@pytest.mark.parametrize("origin", h.main_tier_keeps([(0, 0, 0), (-11, 5, 3)], ((-11, 5, 3),)))
def test_hashed_marching_cubes_equals_the_dense_reference(origin):
  """Same triangles up to order, across block boundaries (the volume spans several blocks)."""
  volume = _blob()
  layer = _layer_from_volume(volume, origin)
  vertices, faces = mesh_lib.marching_cubes(layer)
  ref_v, ref_f = mc_reference.marching_cubes_dense(volume)
  ref_world = (ref_v + np.asarray(origin) + 0.5) * VOXEL
  assert len(faces) == len(ref_f) > 100
  assert _same_triangles(vertices, faces, ref_world, ref_f)


def test_cubes_below_min_weight_are_skipped_like_invalid_corners():
  volume = _blob(seed=1)
  weight = np.ones_like(volume)
  weight[5:8, 4:9, 3:6] = 0.5
  layer = _layer_from_volume(volume, (2, -3, 1), weight=weight)
  vertices, faces = mesh_lib.marching_cubes(layer, min_weight=1.0)
  ref_v, ref_f = mc_reference.marching_cubes_dense(volume, valid=weight >= 1.0)
  ref_world = (ref_v + np.array([2, -3, 1]) + 0.5) * VOXEL
  assert _same_triangles(vertices, faces, ref_world, ref_f)
  assert len(faces) < len(mesh_lib.marching_cubes(layer)[1])


def test_closed_surface_gives_a_watertight_outward_mesh():
  n = 20
  x = np.stack(np.meshgrid(*[np.arange(n, dtype=float)] * 3, indexing="ij"), -1)
  volume = np.clip((np.linalg.norm(x - 9.3, axis=-1) - 6.2) * VOXEL, -0.2, 0.2).astype(np.float32)
  vertices, faces = mesh_lib.marching_cubes(_layer_from_volume(volume, (-4, -9, 2)))
  surface = trimesh.Trimesh(vertices, faces, process=False)
  surface.merge_vertices()
  assert surface.is_watertight and surface.is_winding_consistent
  assert surface.volume > 0                              # normals point out (towards sdf > 0)
  radius = np.linalg.norm(vertices - (np.array([-4, -9, 2]) + 9.3 + 0.5) * VOXEL, axis=1)
  np.testing.assert_allclose(radius, 6.2 * VOXEL, atol=0.1 * VOXEL)


def test_empty_layer_gives_an_empty_mesh():
  rule = jf.rules.bayes()
  state = jf.init_map(capacity=2**8, num_classes=3, rule=rule,
                      geometry=tsdf.TSDFConfig(capacity=2**4))
  m = jf.extract_mesh(state)
  assert m.vertices.shape == (0, 3) and m.faces.shape == (0, 3) and m.labels.shape == (0,)
  assert mesh_lib.marching_cubes(tsdf.init_tsdf(capacity=2**4))[0].shape == (0, 3)
  with pytest.raises(ValueError, match="no geometry layer"):
    jf.extract_mesh(jf.init_map(capacity=2**8, num_classes=3, rule=rule))


@pytest.fixture(scope="module")
def room():
  """The bench room (4 frames, 120×160) fused with D+R and a 5 cm geometry layer."""
  frames = scene.make_frames(4, height=120, width=160, num_classes=7, hole_fraction=0.0)
  rule = jf.rules.robust()
  state = jf.init_map(capacity=2**14, num_classes=7, rule=rule,
                      geometry=tsdf.TSDFConfig(voxel_size=VOXEL, capacity=2**12))
  state = jf.fuse_sequence(state, frames.stacked(), frames.camera, rule)
  return frames, state, jf.extract_mesh(state)


def _room_face_distance(points):
  """Distance of world points to the nearest face of the bench room or of one of its boxes."""
  p = np.asarray(points, np.float64) - scene.OFF_GRID
  boxes = [(scene.ROOM_MIN, scene.ROOM_MAX)] + [(np.array(lo), np.array(hi))
                                                for lo, hi, _ in scene.BOXES]
  out = np.full(len(p), np.inf)
  for lo, hi in boxes:
    q = np.abs(p - (lo + hi) / 2) - (hi - lo) / 2
    d = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(axis=1), 0)
    out = np.minimum(out, np.abs(d))
  return out


def test_bench_room_mesh_lies_on_its_box_faces(room):
  _, _, m = room
  assert m.num_faces > 5000
  distance = _room_face_distance(m.vertices)
  # Measured: 97 % within half a voxel, median 0.16 voxel; the rest round the boxes' edges and
  # corners (the projective distance is not Euclidean there, docs/equations.md §8.3).
  assert np.quantile(distance, 0.95) < 0.5 * VOXEL
  assert np.median(distance) < 0.2 * VOXEL
  assert distance.max() < 4 * VOXEL


def test_vertices_carry_the_semantic_layer(room):
  _, state, m = room
  q = jf.query(state, m.vertices)
  found = np.asarray(q.found)
  assert 0.95 < found.mean() < 1.0
  np.testing.assert_array_equal(m.labels[found], np.asarray(q.posterior).argmax(-1)[found])
  np.testing.assert_allclose(m.confidence[found], np.asarray(q.posterior).max(-1)[found])
  np.testing.assert_allclose(m.entropy[found], np.asarray(q.entropy)[found])
  assert np.all(np.abs(np.linalg.norm(m.normals, axis=1) - 1) < 1e-4)
  # Without fill, a vertex outside the map's voxels has no label.
  bare = jf.extract_mesh(state, fill=False)
  np.testing.assert_array_equal(bare.labels, np.where(found, m.labels, -1))
  np.testing.assert_allclose(bare.entropy, np.asarray(q.entropy))
  # With fill (the default), it reads the nearest of the 26 neighbouring voxels in the map
  # (docs/equations.md §9.2), here found by brute force over the map's voxels.
  voxels = jf.read_map(state)
  label_of = {tuple(c): int(l) for c, l in zip(voxels["coords"], voxels["labels"])}
  size = np.float64(np.float32(state.voxel_size))
  keys = np.asarray(jf.camera.voxel_keys(jnp.asarray(m.vertices), size)[0])
  offsets = [(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
             if (i, j, k) != (0, 0, 0)]
  filled = 0
  for v in np.flatnonzero(~found):
    best, label = np.inf, -1
    for o in offsets:          # the first of equal distances (to a micrometre) wins
      c = tuple(keys[v] + o)
      d = round(float(np.linalg.norm((np.asarray(c) + 0.5) * size
                                     - m.vertices[v].astype(np.float64))), 6)
      if c in label_of and d < best:
        best, label = d, label_of[c]
    assert m.labels[v] == label, (v, m.labels[v], label)
    filled += label >= 0
  assert filled > 0.5 * np.sum(~found)


def test_class_meshes_partition_the_mesh(room):
  _, state, m = room
  per_class = jf.mesh_by_class(state)
  assert len(per_class) >= 3
  assert sum(c.num_faces for c in per_class.values()) == int(np.sum(m.face_labels >= 0))
  whole = _triangle_set(m.vertices, m.faces[m.face_labels >= 0])
  parts = set()
  for c, part in per_class.items():
    assert np.all(part.face_labels == c)
    tris = _triangle_set(part.vertices, part.faces)
    assert not (tris & parts)
    parts |= tris
  assert parts == whole
  some = jf.extract_mesh(state, classes=[0, 5])
  assert _triangle_set(some.vertices, some.faces) == (
      _triangle_set(per_class[0].vertices, per_class[0].faces)
      | _triangle_set(per_class[5].vertices, per_class[5].faces))


def test_box_crop_keeps_faces_whose_centroid_is_inside(room):
  _, state, m = room
  lo, hi = np.array([-1.0, -1.0, 0.0]), np.array([1.0, 1.0, 1.0])
  cropped = jf.extract_mesh(state, box=(lo, hi))
  centroids = m.vertices[m.faces].mean(axis=1)
  inside = np.all((centroids >= lo) & (centroids <= hi), axis=1)
  assert cropped.num_faces == int(inside.sum()) > 0
  assert _triangle_set(cropped.vertices, cropped.faces) == _triangle_set(m.vertices,
                                                                        m.faces[inside])


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".glb"])
def test_export_round_trips(room, tmp_path, suffix):
  _, state, m = room
  path = tmp_path / f"mesh{suffix}"
  colors = np.asarray(jf.datasets.CLASS_COLORS, np.uint8)
  jf.io.save_mesh(path, m, colors=colors, num_classes=7)
  back = trimesh.load(path, force="mesh", process=False)
  assert len(back.faces) == m.num_faces
  assert _same_triangles(m.vertices, m.faces, back.vertices, back.faces, tol=1e-4)
  if suffix == ".ply":
    rgba = np.asarray(back.visual.vertex_colors)
    labelled = m.labels >= 0
    np.testing.assert_array_equal(rgba[labelled, :3], colors[m.labels[labelled]])
    np.testing.assert_array_equal(np.asarray(back.metadata["_ply_raw"]["vertex"]["data"]["label"]),
                                  m.labels)


def test_saved_map_keeps_its_geometry_layer(room, tmp_path):
  frames, state, m = room
  path = tmp_path / "map.npz"
  jf.io.save_map(path, state, jf.rules.robust())
  back, _, _ = jf.io.load_map(path)
  for name in jf.io.GEOMETRY_ARRAYS:
    np.testing.assert_array_equal(np.asarray(getattr(back.geometry, name)),
                                  np.asarray(getattr(state.geometry, name)))
  assert back.geometry.config() == state.geometry.config()
  again = jf.extract_mesh(back)
  np.testing.assert_array_equal(again.vertices, m.vertices)
  np.testing.assert_array_equal(again.faces, m.faces)


@pytest.mark.slow
def test_six_rules_give_bit_identical_maps_with_geometry_on_or_off():
  """Each rule's map with the geometry layer equals, bit for bit, its map without (both fused
  in one compiled program per rule, with `fuse_sequence`'s own body)."""
  frames = scene.make_frames(2, height=48, width=64, num_classes=7)
  geometry = tsdf.TSDFConfig(capacity=2**10)
  for name in ("sum_probs", "sum_labels", "bayes", "R", "D", "D+R"):
    rule = jf.rules.by_name(name)
    off = jf.init_map(capacity=2**12, num_classes=7, rule=rule)
    on = jf.init_map(capacity=2**12, num_classes=7, rule=rule, geometry=geometry)
    both = jax.jit(lambda a, b, f, r: (jf.fusion.fuse_sequence_unchecked(a, f, frames.camera, r),
                                       jf.fusion.fuse_sequence_unchecked(b, f, frames.camera, r)))
    off, on = both(off, on, frames.stacked(), rule)
    assert int(on.geometry.num_blocks) > 0
    for a, b in zip(jax.tree.leaves(off), jax.tree.leaves(on.replace(geometry=None))):
      np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_label_mesh_relabels_one_geometry_for_another_map(room):
  frames, state, m = room
  other_rule = jf.rules.bayes()
  other = jf.init_map(capacity=2**14, num_classes=7, rule=other_rule)
  other = jf.fuse_sequence(other, frames.stacked(), frames.camera, other_rule)
  relabelled = jf.label_mesh(m, other)
  direct = jf.extract_mesh(other.replace(geometry=state.geometry))
  for field in ("vertices", "faces", "labels", "confidence", "entropy", "face_labels"):
    np.testing.assert_array_equal(getattr(relabelled, field), getattr(direct, field), field)
  with pytest.raises(ValueError, match="label_mesh needs one MapState"):
    jf.label_mesh(m, state.geometry)


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 300), st.integers(0, 2**31 - 1), st.sampled_from([2, 40, 2**29]))
def test_unique_keys_inverts_and_lists_each_voxel_once(count, seed, spread):
  """The mesh labels ask once per distinct voxel: `unique[inverse]` gives back every key, each
  voxel is listed once, for compact sets (the mark per cell) and sparse ones (the sort)."""
  rng = np.random.default_rng(seed)
  keys = rng.integers(-spread, spread, size=(count, 3)).astype(np.int32)
  keys[rng.random(count) < 0.3] = keys[0]                 # repeats
  unique, inverse = mesh_lib._unique_keys(keys)
  np.testing.assert_array_equal(unique[inverse], keys)
  assert len(np.unique(unique, axis=0)) == len(unique) == len(np.unique(keys, axis=0))
  assert unique.dtype == np.int32


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 300), st.integers(0, 2**31 - 1), st.sampled_from([8, 1024, 2**20]))
def test_unique_slots_lists_each_held_slot_once(count, seed, capacity):
  """The labels read each held slot once: `_unique_slots` lists the distinct slots in order and
  `index` maps every slot asked for back to its place in that list."""
  slots = np.random.default_rng(seed).integers(0, capacity, count).astype(np.int32)
  unique, index = mesh_lib._unique_slots(slots, capacity)
  np.testing.assert_array_equal(unique, np.unique(slots))
  np.testing.assert_array_equal(unique[index[slots]], slots)


def test_labels_are_a_query_of_every_point_bit_for_bit(room):
  """Asked once per voxel, the labels, confidence and entropy are those of `query` at every
  vertex and face centroid, out-of-range and non-finite points included (not found)."""
  _, state, m = room
  points = np.concatenate([m.vertices, m.vertices[m.faces].mean(axis=1)]).astype(np.float32)
  points[:3] = [[np.nan, 0, 0], [1e12, 0, 0], [0, -np.inf, 0]]
  labels, confidence, entropy = mesh_lib._read_labels(state, points, fill=False)
  q = jf.query(state, points)
  found = np.asarray(q.found)
  assert not found[:3].any() and found.mean() > 0.9
  np.testing.assert_array_equal(labels, np.where(found, np.asarray(q.posterior).argmax(-1), -1))
  np.testing.assert_array_equal(confidence,
                                np.where(found, np.asarray(q.posterior).max(-1), 0.0))
  np.testing.assert_array_equal(entropy, np.asarray(q.entropy))


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 200), st.integers(0, 2**31 - 1), st.sampled_from([0.02, 0.05, 0.1]))
def test_fill_picks_the_nearest_neighbour_in_the_map(count, seed, voxel_size):
  """The fill's search (`_nearest_found`, a vectorised pass one axis at a time) picks what the
  per-point loop of §9.2 picks: the nearest of the neighbours in the map, distances in float64
  rounded to a micrometre, the first of equal ones — points on voxel faces, edges and corners
  (exact ties) included."""
  rng = np.random.default_rng(seed)
  size = np.float64(np.float32(voxel_size))
  keys = rng.integers(-50, 50, size=(count, 3)).astype(np.int32)
  # Offsets within the voxel: random, or on its faces and corners (ties between centres).
  within = np.where(rng.random((count, 3)) < 0.5, rng.choice([0.0, 0.5, 1.0], (count, 3)),
                    rng.random((count, 3)))
  points = ((keys + within) * size).astype(np.float32)
  near_found = rng.random((count, 26)) < rng.uniform(0.05, 0.9)
  near_found[np.arange(count), rng.integers(0, 26, count)] = True
  best = mesh_lib._nearest_found(keys, points, near_found, voxel_size)
  offsets = mesh_lib._VOXEL_NEIGHBOURS
  for i in range(count):
    distances = [round(float(np.linalg.norm((keys[i] + offsets[n] + 0.5) * size
                                            - points[i].astype(np.float64))), 6)
                 if near_found[i, n] else np.inf for n in range(26)]
    assert best[i] == int(np.argmin(distances)), (i, best[i], distances)


@given(st.integers(0, 2**31))
def test_mesh_buffers_are_padded_by_at_most_an_eighth(n):
  """The meshing buffers (`_bucket`) hold every entry asked for, waste at most 1/8 of them
  past 16, and take few sizes: 8 an octave."""
  b = mesh_lib._bucket(n)
  assert b >= max(n, 1) and (b <= 16 or b <= n + n // 8 + 1)
  assert b % (1 << max(b.bit_length() - 4, 0)) == 0
