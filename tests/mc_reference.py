"""A slow, obvious marching cubes on a dense NumPy volume, for tests: plain loops over cubes,
the case tables of `jaxfusion.mc_tables`, one shared vertex per (owner voxel, axis) edge."""

import numpy as np

from jaxfusion import mc_tables


def marching_cubes_dense(volume, level=0.0, valid=None, *, spacing=1.0, origin=(0.0, 0.0, 0.0)):
  """Triangles of the `level` set of `volume (X, Y, Z)`.

  A cube is skipped when one of its 8 corners has `valid == False`. Vertices are in voxel index
  units times `spacing`, plus `origin`.

  Returns:
    `(vertices (V, 3) float64, faces (F, 3) int64)`.
  """
  volume = np.asarray(volume, np.float64)
  valid = np.ones(volume.shape, bool) if valid is None else np.asarray(valid, bool)
  index = {}
  vertices, faces = [], []

  def vertex(owner, axis):
    key = (owner, axis)
    if key not in index:
      other = list(owner)
      other[axis] += 1
      v0, v1 = volume[owner], volume[tuple(other)]
      t = (level - v0) / (v1 - v0)
      p = np.array(owner, np.float64)
      p[axis] += t
      index[key] = len(vertices)
      vertices.append(p * spacing + np.asarray(origin, np.float64))
    return index[key]

  nx, ny, nz = volume.shape
  for i in range(nx - 1):
    for j in range(ny - 1):
      for k in range(nz - 1):
        corners = [(i + dx, j + dy, k + dz) for dx, dy, dz in mc_tables.CORNER_OFFSETS]
        if not all(valid[c] for c in corners):
          continue
        case = sum(1 << c for c, p in enumerate(corners) if volume[p] < level)
        for tri in mc_tables.TRIANGLES[case][:mc_tables.NUM_TRIANGLES[case]]:
          ids = []
          for e in tri:
            o = mc_tables.EDGE_OWNER[e]
            ids.append(vertex((i + int(o[0]), j + int(o[1]), k + int(o[2])),
                              int(mc_tables.EDGE_AXIS[e])))
          faces.append(ids)
  return (np.asarray(vertices, np.float64).reshape(-1, 3),
          np.asarray(faces, np.int64).reshape(-1, 3))
