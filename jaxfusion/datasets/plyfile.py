"""Labelled triangle meshes as PLY files, in the layout of ScanNet's `*_vh_clean_2.labels.ply`.

ScanNet ships each scene's ground truth as a mesh whose vertices carry a NYU40 class id:

```
ply
format binary_little_endian 1.0
element vertex V
property float x             ┐
property float y             │ position
property float z             ┘
property uchar red           ┐
property uchar green         │ colour of the vertex's class
property uchar blue          │
property uchar alpha         ┘
property ushort label        NYU40 id (0 = unannotated)
element face F
property list uchar int vertex_indices
end_header
```
`write_labelled_mesh` writes exactly that; `read_labelled_mesh` reads it back, and any other
PLY (ASCII or binary, either byte order, extra properties or elements) whose vertices have a
`label` property. `read_ply` gives every element and property of a PLY file.

Shape legend: V vertices, F triangles.
"""

import os

import numpy as np

from jaxfusion import io

_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
_FACE_LISTS = ("vertex_indices", "vertex_index")


def label_colors(labels: np.ndarray) -> np.ndarray:
  """`(V, 4) uint8` RGBA of fixed, distinct-looking colours per class id (0, unannotated:
  black), for meshes written without colours.

  Args:
    labels: `(V,) int` class ids.
  """
  labels = np.asarray(labels, np.int64)
  rgba = np.full((len(labels), 4), 255, np.uint8)
  steps = np.array([0.6180339887, 0.4142135624, 0.7320508076])
  rgba[:, :3] = np.round(55.0 + 200.0 * ((labels[:, None] * steps) % 1.0)).astype(np.uint8)
  rgba[labels == 0, :3] = 0
  return rgba


def check_labelled_mesh(mesh: dict) -> tuple:
  """Checks a labelled mesh dict (see `write_labelled_mesh`).

  Returns:
    `(vertices (V, 3) float32, faces (F, 3) int32, labels (V,) uint16, colors (V, 4) uint8)`.

  Raises:
    ValueError: a missing key, or an array of the wrong shape, type or range.
  """
  try:
    vertices, faces, labels = (np.asarray(mesh[k]) for k in ("vertices", "faces", "labels"))
  except (KeyError, TypeError) as e:
    raise ValueError("a labelled mesh is a dict with 'vertices', 'faces' and 'labels'") from e
  if vertices.ndim != 2 or vertices.shape[1] != 3 or not np.all(np.isfinite(vertices)):
    raise ValueError(f"mesh vertices must be finite (V, 3); got shape {vertices.shape}")
  n = len(vertices)
  faces = faces.reshape(-1, 3) if faces.size == 0 else faces
  if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
    raise ValueError(f"mesh faces must be (F, 3) integers; got {faces.shape} {faces.dtype}")
  if faces.size and (faces.min() < 0 or faces.max() >= n):
    raise ValueError(f"mesh faces index vertices outside [0, {n})")
  if labels.shape != (n,) or not np.issubdtype(labels.dtype, np.integer):
    raise ValueError(f"mesh labels must be ({n},) integers; got {labels.shape} {labels.dtype}")
  if labels.size and (labels.min() < 0 or labels.max() > 65535):
    raise ValueError("mesh labels must lie in [0, 65535] (stored as ushort)")
  colors = mesh.get("colors")
  if colors is None:
    colors = label_colors(labels)
  colors = np.asarray(colors)
  if colors.shape in ((n, 3),):
    colors = np.concatenate([colors, np.full((n, 1), 255, colors.dtype)], axis=1)
  if colors.shape != (n, 4) or colors.dtype != np.uint8:
    raise ValueError(f"mesh colors must be ({n}, 3) or ({n}, 4) uint8; got {colors.shape} "
                     f"{colors.dtype}")
  return (vertices.astype(np.float32), faces.astype(np.int32), labels.astype(np.uint16),
          colors)


def write_labelled_mesh(path: str, mesh: dict, *, comment: str = "written by jaxfusion"
                        ) -> str:
  """Writes a labelled mesh as a binary little-endian PLY in ScanNet's `labels.ply` layout.

  Args:
    path: the `.ply` file (written atomically).
    mesh: dict with `vertices (V, 3) float`, `faces (F, 3) int`, `labels (V,) int` (NYU40
      ids in [0, 65535]) and optionally `colors (V, 3|4) uint8` (default: `label_colors`).
    comment: a `comment` line of the header.

  Returns:
    The path.
  """
  vertices, faces, labels, colors = check_labelled_mesh(mesh)
  if "\n" in comment or "\r" in comment:
    raise ValueError("a PLY comment must be one line")
  header = "\n".join([
      "ply", "format binary_little_endian 1.0", f"comment {comment}",
      f"element vertex {len(vertices)}",
      "property float x", "property float y", "property float z",
      "property uchar red", "property uchar green", "property uchar blue",
      "property uchar alpha", "property ushort label",
      f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header", ""])
  vertex = np.empty(len(vertices), [("xyz", "<f4", (3,)), ("rgba", "u1", (4,)), ("label", "<u2")])
  vertex["xyz"], vertex["rgba"], vertex["label"] = vertices, colors, labels
  face = np.empty(len(faces), [("count", "u1"), ("indices", "<i4", (3,))])
  face["count"], face["indices"] = 3, faces

  def write(tmp):
    with open(tmp, "wb") as f:
      f.write(header.encode("ascii"))
      f.write(vertex.tobytes())
      f.write(face.tobytes())

  io.atomic_write(path, write)
  return path


def _parse_header(path: str, data: bytes) -> tuple:
  """`(format, elements, body offset)`: elements are `(name, count, [(prop, type, list
  count type or None)])`."""
  end = data.find(b"end_header")
  if not data.startswith(b"ply") or end < 0:
    raise io.BadFileError(f"{path} is not a PLY file (no 'ply' ... 'end_header' header)")
  newline = data.find(b"\n", end)
  if newline < 0:
    raise io.BadFileError(f"{path}: the PLY header does not end with a newline")
  try:
    lines = data[:end].decode("ascii").splitlines()
  except UnicodeDecodeError as e:
    raise io.BadFileError(f"{path}: the PLY header is not ASCII text") from e
  fmt, elements = None, []
  for line in lines[1:]:
    parts = line.split()
    if not parts or parts[0] in ("comment", "obj_info"):
      continue
    try:
      if parts[0] == "format":
        if parts[1] not in _FORMATS:
          raise io.BadFileError(f"{path}: unknown PLY format {parts[1]!r}")
        fmt = parts[1]
      elif parts[0] == "element":
        elements.append((parts[1], int(parts[2]), []))
      elif parts[0] == "property" and parts[1] == "list":
        elements[-1][2].append((parts[4], _TYPES[parts[3]], _TYPES[parts[2]]))
      elif parts[0] == "property":
        elements[-1][2].append((parts[2], _TYPES[parts[1]], None))
      else:
        raise io.BadFileError(f"{path}: bad PLY header line {line!r}")
    except (IndexError, KeyError, ValueError) as e:
      if isinstance(e, io.BadFileError):
        raise
      raise io.BadFileError(f"{path}: bad PLY header line {line!r}") from e
  if fmt is None:
    raise io.BadFileError(f"{path}: the PLY header has no 'format' line")
  if any(count < 0 for _, count, _ in elements):
    raise io.BadFileError(f"{path}: negative element count in the PLY header")
  return fmt, elements, newline + 1


def _read_binary_element(path, data, offset, order, name, count, props) -> tuple:
  """`({property: array}, new offset)` of one element of a binary PLY."""
  lists = [p for p in props if p[2] is not None]
  short = io.BadFileError(f"{path} is cut short (in element {name!r})")
  if count == 0:
    return {p: np.zeros((0,) if c is None else (0, 0), t) for p, t, c in props}, offset
  if not lists:
    dtype = np.dtype([(p, order + t) for p, t, _ in props])
    if offset + count * dtype.itemsize > len(data):
      raise short
    rows = np.frombuffer(data, dtype, count, offset)
    return {p: rows[p].copy() for p, _, _ in props}, offset + count * dtype.itemsize
  # Fast path: every list has the length of the first row's (triangles: 3).
  lengths, pos = [], offset
  for p, t, count_type in props:
    if count_type is None:
      pos += np.dtype(t).itemsize
      continue
    if pos + np.dtype(count_type).itemsize > len(data):
      raise short
    k = int(np.frombuffer(data, order + count_type, 1, pos)[0])
    lengths.append(k)
    pos += np.dtype(count_type).itemsize + k * np.dtype(t).itemsize
  fields, it = [], iter(lengths)
  for p, t, count_type in props:
    if count_type is None:
      fields.append((p, order + t))
    else:
      fields += [(f"{p}.count", order + count_type), (p, order + t, (next(it),))]
  dtype = np.dtype(fields)
  if offset + count * dtype.itemsize <= len(data):
    rows = np.frombuffer(data, dtype, count, offset)
    if all(np.all(rows[f"{p}.count"] == k) for (p, _, _), k in zip(lists, lengths)):
      return {p: rows[p].copy() for p, _, _ in props}, offset + count * dtype.itemsize
  # General path: lists of varying lengths, read row by row.
  out = {p: [] for p, _, _ in props}
  pos = offset
  for _ in range(count):
    for p, t, count_type in props:
      size = np.dtype(t).itemsize
      if count_type is None:
        if pos + size > len(data):
          raise short
        out[p].append(np.frombuffer(data, order + t, 1, pos)[0])
        pos += size
        continue
      csize = np.dtype(count_type).itemsize
      if pos + csize > len(data):
        raise short
      k = int(np.frombuffer(data, order + count_type, 1, pos)[0])
      pos += csize
      if pos + k * size > len(data):
        raise short
      out[p].append(np.frombuffer(data, order + t, k, pos).copy())
      pos += k * size
  return {p: (v if count_type is not None else np.array(v, t))
          for (p, t, count_type), v in zip(props, out.values())}, pos


def _read_ascii_element(path, tokens, pos, name, count, props) -> tuple:
  """`({property: array}, new token position)` of one element of an ASCII PLY."""
  short = io.BadFileError(f"{path} is cut short (in element {name!r})")
  try:
    if all(c is None for _, _, c in props):
      n = count * len(props)
      if pos + n > len(tokens):
        raise short
      rows = np.array(tokens[pos:pos + n], np.float64).reshape(count, len(props))
      return {p: rows[:, i].astype(t) for i, (p, t, _) in enumerate(props)}, pos + n
    out = {p: [] for p, _, _ in props}
    for _ in range(count):
      for p, t, count_type in props:
        if pos >= len(tokens):
          raise short
        if count_type is None:
          out[p].append(float(tokens[pos]))
          pos += 1
          continue
        k = int(tokens[pos])
        if k < 0 or pos + 1 + k > len(tokens):
          raise short
        out[p].append(np.array(tokens[pos + 1:pos + 1 + k], np.float64).astype(t))
        pos += 1 + k
  except ValueError as e:
    if isinstance(e, io.BadFileError):
      raise
    raise io.BadFileError(f"{path}: a value of element {name!r} is not a number") from e
  result = {}
  for p, t, count_type in props:
    values = out[p]
    if count_type is None:
      result[p] = np.array(values, t)
    elif values and all(len(v) == len(values[0]) for v in values):
      result[p] = np.stack(values)
    else:
      result[p] = values
  return result, pos


def read_ply(path: str) -> dict:
  """Every element of a PLY file (ASCII or binary).

  Args:
    path: the `.ply` file.

  Returns:
    `{element: {property: array}}`, in the file's order: a scalar property is an `(N,)`
    array of its type; a list property an `(N, k)` array when all its lists have k entries,
    else a list of N arrays.

  Raises:
    FileNotFoundError: no file at `path`.
    BadFileError: (a `ValueError`) not a PLY file, or a header or body that cannot be read;
      the message names the file.
  """
  if not os.path.isfile(path):
    raise FileNotFoundError(f"missing file: {path}")
  with open(path, "rb") as f:
    data = f.read()
  fmt, elements, offset = _parse_header(path, data)
  out = {}
  if fmt == "ascii":
    try:
      tokens = data[offset:].decode("ascii").split()
    except UnicodeDecodeError as e:
      raise io.BadFileError(f"{path}: the body of an ASCII PLY is not text") from e
    pos = 0
    for name, count, props in elements:
      out[name], pos = _read_ascii_element(path, tokens, pos, name, count, props)
  else:
    order = _FORMATS[fmt]
    for name, count, props in elements:
      out[name], offset = _read_binary_element(path, data, offset, order, name, count, props)
  return out


def _triangles(path: str, faces) -> np.ndarray:
  """`(F, 3) int32` triangles of a face list property (polygons split into fans)."""
  if isinstance(faces, np.ndarray) and faces.ndim == 2 and faces.shape[1] == 3:
    return faces.astype(np.int32)
  polygons = list(faces)
  tris = [np.stack([np.full(len(p) - 2, p[0]), p[1:-1], p[2:]], -1) for p in polygons
          if len(p) >= 3]
  if len(tris) != len(polygons):
    raise io.BadFileError(f"{path}: a face has fewer than 3 vertices")
  return np.concatenate(tris).astype(np.int32) if tris else np.zeros((0, 3), np.int32)


def read_labelled_mesh(path: str) -> dict:
  """Reads a labelled mesh such as ScanNet's `<scene>_vh_clean_2.labels.ply`.

  Args:
    path: a PLY file (ASCII or binary) whose vertices have `x y z` and `label`.

  Returns:
    dict with `vertices (V, 3) float32`, `faces (F, 3) int32` (polygons split into
    triangles; `(0, 3)` for a point cloud) and `labels (V,) int32` (NYU40 ids for ScanNet).

  Raises:
    FileNotFoundError: no file at `path`.
    BadFileError: (a `ValueError`) not a PLY file, no `vertex` element with `x y z`, no
      `label` vertex property, or faces that index missing vertices.
  """
  ply = read_ply(path)
  vertex = ply.get("vertex")
  if vertex is None or not {"x", "y", "z"} <= set(vertex):
    raise io.BadFileError(f"{path} has no vertex element with x, y and z properties")
  if "label" not in vertex:
    raise io.BadFileError(f"{path} has no 'label' vertex property (not a labelled mesh such "
                          "as ScanNet's *_vh_clean_2.labels.ply)")
  vertices = np.stack([vertex[k] for k in ("x", "y", "z")], -1).astype(np.float32)
  faces = np.zeros((0, 3), np.int32)
  face = ply.get("face", {})
  name = next((k for k in _FACE_LISTS if k in face), None)
  if name is not None:
    faces = _triangles(path, face[name])
  if faces.size and (faces.min() < 0 or faces.max() >= len(vertices)):
    raise io.BadFileError(f"{path}: faces index vertices outside [0, {len(vertices)})")
  return {"vertices": vertices, "faces": faces,
          "labels": np.asarray(vertex["label"]).astype(np.int32)}

