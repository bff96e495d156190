"""One writer for the commands' reports: Markdown/text, CSV and JSON, each written atomically
(to a temporary file, then renamed: a report on disk is either whole or absent).
"""

import csv
import io as _io
import json
from typing import Iterable, Optional, Sequence

import numpy as np

from jaxfusion import io


def jsonable(x):
  """`x` with NumPy arrays and scalars as Python values, named tuples as dicts, dict keys as
  strings, and non-finite floats as None (so the file is strict JSON)."""
  if isinstance(x, dict):
    return {str(k): jsonable(v) for k, v in x.items()}
  if isinstance(x, tuple) and hasattr(x, "_asdict"):
    return jsonable(x._asdict())
  if isinstance(x, (list, tuple)):
    return [jsonable(v) for v in x]
  if isinstance(x, np.ndarray):
    return jsonable(x.tolist())
  if isinstance(x, (bool, np.bool_)):
    return bool(x)
  if isinstance(x, np.integer):
    return int(x)
  if isinstance(x, (float, np.floating)):
    return float(x) if np.isfinite(x) else None
  return x


def write_text(path: str, text: str) -> str:
  """Writes `text` (UTF-8) to `path`; returns the path."""

  def write(tmp):
    with open(tmp, "w", encoding="utf-8") as f:
      f.write(text)

  io.atomic_write(path, write)
  return path


def write_json(path: str, payload, *, indent: Optional[int] = 1) -> str:
  """Writes `jsonable(payload)` as JSON; returns the path."""
  return write_text(path, json.dumps(jsonable(payload), indent=indent))


def csv_text(rows: Iterable[Sequence], header: Optional[Sequence[str]] = None) -> str:
  """CSV text of `rows` (sequences of cells), after an optional header row."""
  buf = _io.StringIO()
  writer = csv.writer(buf)
  if header is not None:
    writer.writerow(list(header))
  for row in rows:
    writer.writerow(list(row))
  return buf.getvalue()


def write_csv(path: str, rows: Iterable[Sequence], header: Optional[Sequence[str]] = None
              ) -> str:
  """Writes `rows` as CSV after an optional header row; returns the path."""
  return write_text(path, csv_text(rows, header))
