"""Marching-cubes case tables, generated here by an algorithm (no published table is copied).

Conventions (the jitted kernel in `mesh` depends on them exactly):
- A cube has corners c = 0…7 at integer offset `(c & 1, c >> 1 & 1, c >> 2 & 1)` along
  (x, y, z), the axes (0, 1, 2) of a volume `v[i, j, k]`.
- Case index `Σ_c [value_c < level] << c`: a corner is *inside* when below the level (for a TSDF:
  behind the surface).
- Edge e = 0…11 runs along axis `a = e // 4`. With (b, c) the other two axes in increasing order
  and q = e % 4, its *owner* corner has offset 0 along a, `q & 1` along b and `q >> 1` along c;
  the edge goes from the owner to owner + unit(a). So every voxel owns the three edges that
  leave it along +x, +y, +z, and a vertex is shared by all cubes around its edge.
- A vertex lies at `owner + t·unit(a)`, `t = (level − v_owner) / (v_other − v_owner)`.
- `TRIANGLES[case]` holds up to 5 triangles of edge ids (−1 padding), `NUM_TRIANGLES[case]` how
  many. Triangles are oriented so that `(p1 − p0) × (p2 − p0)` points from inside to outside,
  along the field's gradient.

How the table is built (`build_tables`), per case:
1. On each of the cube's 6 faces, walk its 4 corners counter-clockwise as seen from outside the
   cube. Each face edge whose ends differ in sign carries a crossing, entering (outside → inside)
   or leaving (inside → outside). Every entering crossing is joined, by a directed segment on that
   face, to the next leaving crossing in the walk. On a face with 4 crossings (two diagonal
   inside corners, the ambiguous face) this cuts off each inside corner separately: the inside
   corners are never joined across a face. The rule reads only the face's corner signs, and a
   cube on the other side of the face walks it the other way round, so two cubes sharing a face
   draw the same segments in opposite directions: the surface has no cracks and a closed
   surface gives a watertight, consistently wound mesh.
2. Each crossing edge is shared by two faces, where it ends one segment and starts another, so
   the segments link into closed loops: the cube's surface polygons.
3. Each polygon is triangulated as a fan from the first of its vertices none of whose
   diagonals joins two vertices on one cube face (such a diagonal lies in the face, where the
   neighbouring cube may draw the same segment, and the surface would pinch); the winding from
   step 1 puts the normal from inside to outside.

Compared with `skimage.measure.marching_cubes(method="lorensen")` (tests/engine/
test_mc_tables.py): the same vertices (skimage merges a few that nearly coincide) and the same
surface area to 0.5 %; the triangles themselves differ where a polygon of 4–6 vertices is split
along another diagonal, and on ambiguous faces where the two tables resolve them differently
(skimage's classic table is not consistent across them; this one is, so it has no cracks).
"""

import numpy as np

CORNER_OFFSETS = np.array([[c & 1, (c >> 1) & 1, (c >> 2) & 1] for c in range(8)], np.int32)


def _edges():
  axis = np.zeros(12, np.int32)
  owner = np.zeros((12, 3), np.int32)
  corners = np.zeros((12, 2), np.int32)
  for e in range(12):
    a = e // 4
    b, c = [i for i in range(3) if i != a]
    q = e % 4
    o = np.zeros(3, np.int32)
    o[b], o[c] = q & 1, q >> 1
    axis[e], owner[e] = a, o
    other = o.copy()
    other[a] = 1
    corners[e] = [o[0] + 2 * o[1] + 4 * o[2], other[0] + 2 * other[1] + 4 * other[2]]
  return axis, owner, corners


EDGE_AXIS, EDGE_OWNER, EDGE_CORNERS = _edges()
_EDGE_OF = {frozenset(map(int, pair)): e for e, pair in enumerate(EDGE_CORNERS)}


def _faces():
  """The 6 faces' corners, counter-clockwise seen from outside (outward normal)."""
  faces = []
  for a in range(3):
    for side in (0, 1):
      corners = [c for c in range(8) if CORNER_OFFSETS[c, a] == side]
      centre = CORNER_OFFSETS[corners].mean(axis=0)
      b, c = [i for i in range(3) if i != a]
      angle = [np.arctan2(CORNER_OFFSETS[k, c] - centre[c], CORNER_OFFSETS[k, b] - centre[b])
               for k in corners]
      ring = [corners[i] for i in np.argsort(angle)]
      normal = np.zeros(3)
      normal[a] = 2 * side - 1
      p = CORNER_OFFSETS[ring].astype(float)
      if np.cross(p[1] - p[0], p[2] - p[1]) @ normal < 0:
        ring = ring[::-1]
      faces.append(ring)
  return faces


_FACES = _faces()


def _polygons(case: int) -> list:
  """The case's surface polygons, each a list of edge ids in winding order."""
  inside = [(case >> c) & 1 == 1 for c in range(8)]
  following = {}
  for ring in _FACES:
    crossings = []          # (position in the walk, edge, entering?)
    for i in range(4):
      a, b = ring[i], ring[(i + 1) % 4]
      if inside[a] != inside[b]:
        crossings.append((i, _EDGE_OF[frozenset((a, b))], inside[b]))
    for k, (_, edge, entering) in enumerate(crossings):
      if not entering:
        continue
      for step in range(1, len(crossings)):
        _, other, other_entering = crossings[(k + step) % len(crossings)]
        if not other_entering:
          assert edge not in following
          following[edge] = other
          break
  polygons, seen = [], set()
  for start in sorted(following):
    if start in seen:
      continue
    loop, edge = [], start
    while edge not in seen:
      seen.add(edge)
      loop.append(edge)
      edge = following[edge]
    assert edge == start, (case, loop)
    polygons.append(loop)
  return polygons


def _share_a_face(e1: int, e2: int) -> bool:
  corners = set(map(int, EDGE_CORNERS[e1])) | set(map(int, EDGE_CORNERS[e2]))
  return any(corners <= set(ring) for ring in _FACES)


def _fan(loop: list) -> list:
  """Fan triangles of a polygon from the first vertex (in loop order) none of whose diagonals
  joins two vertices on one cube face: such a diagonal lies in the face's plane, where the
  neighbouring cube's polygon can draw the same segment, and the surface would pinch there."""
  n = len(loop)
  for start in range(n):
    ring = loop[start:] + loop[:start]
    if all(not _share_a_face(ring[0], ring[i]) for i in range(2, n - 1)):
      return [(ring[0], ring[i], ring[i + 1]) for i in range(1, n - 1)]
  raise AssertionError(f"no fan apex for polygon {loop}")


def build_tables():
  """`(TRIANGLES (256, 5, 3) int8, NUM_TRIANGLES (256,) int32)` by the algorithm above."""
  triangles = np.full((256, 5, 3), -1, np.int8)
  counts = np.zeros(256, np.int32)
  for case in range(256):
    tris = []
    for loop in _polygons(case):
      tris += _fan(loop)
    assert len(tris) <= 5, case
    counts[case] = len(tris)
    if tris:
      triangles[case, :len(tris)] = tris
  return triangles, counts


TRIANGLES, NUM_TRIANGLES = build_tables()
