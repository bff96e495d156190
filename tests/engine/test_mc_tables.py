"""The generated marching-cubes tables: sanity per case, and the dense reference against
`skimage.measure.marching_cubes` and on closed surfaces."""

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import cKDTree
from skimage import measure

from jaxfusion import mc_tables
from tests.mc_reference import marching_cubes_dense


def test_every_triangle_uses_edges_that_cross():
  assert mc_tables.NUM_TRIANGLES[0] == mc_tables.NUM_TRIANGLES[255] == 0
  for case in range(256):
    inside = [(case >> c) & 1 for c in range(8)]
    crossing = {e for e, (a, b) in enumerate(mc_tables.EDGE_CORNERS) if inside[a] != inside[b]}
    tris = mc_tables.TRIANGLES[case]
    n = mc_tables.NUM_TRIANGLES[case]
    assert np.all(tris[n:] == -1) and np.all(tris[:n] >= 0)
    used = set(tris[:n].reshape(-1).tolist())
    assert used == crossing, case            # every crossing edge carries a vertex of a triangle
    # complement: same triangles, opposite winding
    comp = mc_tables.TRIANGLES[255 - case][:mc_tables.NUM_TRIANGLES[255 - case]]
    if not _ambiguous(case):
      assert {frozenset(t) for t in tris[:n].tolist()} == {frozenset(t) for t in comp.tolist()}


def _ambiguous(case):
  inside = [(case >> c) & 1 for c in range(8)]
  for ring in mc_tables._FACES:
    s = [inside[c] for c in ring]
    if s[0] == s[2] != s[1] == s[3]:
      return True
  return False


def test_edge_conventions():
  for e in range(12):
    a = mc_tables.EDGE_AXIS[e]
    o, other = (mc_tables.CORNER_OFFSETS[c] for c in mc_tables.EDGE_CORNERS[e])
    np.testing.assert_array_equal(o, mc_tables.EDGE_OWNER[e])
    np.testing.assert_array_equal(other - o, np.eye(3, dtype=int)[a])


def test_single_corner_triangle_points_out_of_the_inside_corner():
  for c in range(8):
    tri = mc_tables.TRIANGLES[1 << c, 0]
    p = [mc_tables.EDGE_OWNER[e] + 0.5 * np.eye(3)[mc_tables.EDGE_AXIS[e]] for e in tri]
    normal = np.cross(p[1] - p[0], p[2] - p[0])
    assert normal @ (np.mean(p, axis=0) - mc_tables.CORNER_OFFSETS[c]) > 0


def _grid(n):
  return np.stack(np.meshgrid(*[np.arange(n, dtype=float)] * 3, indexing="ij"), -1)


def _volumes():
  x = _grid(16)
  rng = np.random.default_rng(3)
  yield "sphere", np.linalg.norm(x - 7.3, axis=-1) - 5.1
  yield "plane", x @ np.array([0.3, -0.5, 0.8]) - 4.1
  yield "blobs", np.minimum(np.linalg.norm(x - [5.2, 5.1, 7.0], axis=-1) - 3.4,
                            np.linalg.norm(x - [10.3, 9.8, 7.7], axis=-1) - 3.9)
  field = np.zeros((16, 16, 16))
  for _ in range(6):
    c, r = rng.uniform(2, 14, 3), rng.uniform(1.5, 4)
    field += np.exp(-np.sum((x - c) ** 2, -1) / r**2)
  yield "smooth noise", 0.5 - field


@pytest.mark.parametrize("name, volume", list(_volumes()), ids=[n for n, _ in _volumes()])
def test_reference_matches_skimage(name, volume):
  """The same surface as skimage's Lorensen marching cubes: every skimage vertex is one of ours
  (within its float32 rounding) and vice versa up to the few vertices skimage merges when they
  nearly coincide, and the same area up to the triangulation of non-planar polygons."""
  verts, faces = marching_cubes_dense(volume)
  sk_verts, sk_faces, _, _ = measure.marching_cubes(volume, 0.0, method="lorensen")
  sk_verts = sk_verts[np.unique(sk_faces)]
  distance, _ = cKDTree(verts).query(sk_verts)
  assert distance.max() < 1e-5
  back, _ = cKDTree(sk_verts).query(verts)
  assert np.mean(back < 1e-5) > 0.99 and back.max() < 0.05
  area = trimesh.Trimesh(verts, faces, process=False).area
  sk_area = trimesh.Trimesh(*measure.marching_cubes(volume, 0.0, method="lorensen")[:2],
                            process=False).area
  np.testing.assert_allclose(area, sk_area, rtol=5e-3)


@pytest.mark.parametrize("shape", ["sphere", "torus", "blobs"])
def test_closed_surfaces_are_watertight_and_outward(shape):
  x = _grid(18) - 8.6
  if shape == "sphere":
    field = np.linalg.norm(x, axis=-1) - 6.0
  elif shape == "torus":
    field = np.hypot(np.hypot(x[..., 0], x[..., 1]) - 5.0, x[..., 2]) - 2.2
  else:
    field = np.minimum(np.linalg.norm(x - 2.1, axis=-1) - 4.0,
                       np.linalg.norm(x + 2.3, axis=-1) - 3.7)
  verts, faces = marching_cubes_dense(field)
  mesh = trimesh.Trimesh(verts, faces, process=False)
  assert mesh.is_watertight and mesh.is_winding_consistent
  assert mesh.volume > 0


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_random_volumes_give_closed_consistent_meshes(seed):
  """Random values inside a border of +1: every mesh edge has exactly two faces (no cracks,
  ambiguous faces included) and every vertex lies on its edge."""
  rng = np.random.default_rng(seed)
  volume = np.ones((6, 6, 6))
  volume[1:5, 1:5, 1:5] = rng.uniform(-1, 1, (4, 4, 4))
  verts, faces = marching_cubes_dense(volume)
  if len(faces) == 0:
    return
  frac = verts - np.floor(verts)
  assert np.all(np.sum(frac > 1e-12, axis=1) <= 1)
  mesh = trimesh.Trimesh(verts, faces, process=False)
  assert mesh.is_winding_consistent
  edges = np.sort(mesh.edges, axis=1)
  _, counts = np.unique(edges, axis=0, return_counts=True)
  assert np.all(counts == 2)
