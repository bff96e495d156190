"""Class maps: from the network's classes to the map's.

A network trained on one label set (NYU40, ADE20K, ...) can feed a map with another (the paper's
12 ScanNet classes, the ScanNet benchmark's 20, the embedded world's 7). A `ClassMap` holds the
`(K_src, K_dst)` 0/1 matrix `A` with `A[i, j] = 1` when source class i goes to target class j
(at most one 1 per row), and remaps a frame's MC moments before fusion:

* **many-to-one**: `p'_j = Σ_{i→j} p_i`, i.e. `p' = p A`;
* **variance of a sum**: `var'_j = Σ_{i→j} var_i`, i.e. `var' = var A`. This assumes the summed
  classes' samples are uncorrelated; softmax outputs rarely are (they share one unit of mass,
  so they are typically negatively correlated and the sum over-estimates the variance), so the
  result is also clipped to `p'_j (1 − p'_j)`, the largest variance a [0, 1]-valued probability
  with mean `p'_j` can have — which can only bring it closer to the truth. When the samples are
  at hand, remap them instead (`remap_samples`, then `mc_moments`): that path is exact;
* **unmapped** source classes (no target) are either summed into a named "other" target class
  (`unmapped="other"`: `A` stays a plain sum, nothing is approximated), or dropped
  (`unmapped="drop"`): `p'` is renormalised by its mass `s = Σ_j (p A)_j` (the distribution
  conditioned on "one of the kept classes"; `s ≤ MIN_MASS` gives the uniform distribution) and
  `var'` scaled by `1/s²` (the delta method with s treated as a constant; then clipped as
  above, so at `s ≤ MIN_MASS` it is `(1/K_dst)(1 − 1/K_dst)`, the most a uniform mean allows).

The default for unmapped classes (`unmapped=None`): there is nothing to choose when every source
class has a target; otherwise they go to the "other" class when the target classes have one
(mass kept, the map stays a plain sum), and without one `from_table` raises a `ValueError` that
asks for a choice — dropping changes the remaining probabilities and inventing a class changes
the map's classes, neither of which should happen silently.

Example:
  >>> cm = ClassMap.from_table({"armchair": "chair", "stool": "chair", "desk": "table"},
  ...                          source_classes=["armchair", "stool", "desk", "lamp"],
  ...                          target_classes=["chair", "table"], unmapped="drop")
  >>> probs, var = cm.remap(pred.probs, pred.var)            # (H, W, 4) → (H, W, 2)
  >>> probs, var = mc_moments(cm.remap_samples(samples))      # exact, from (M, H, W, 4)

Files (`ClassMap.from_file`, `.json` or `.csv`):

* JSON — an object with `"map"`: `{source: target}` (or a list of `[source, target]` pairs),
  each a class name or an index, target `null` for unmapped; `"source_classes"`: the network's
  K_src class names in its output order, or the number K_src (names "0" ... "K_src−1"; default:
  the keys of "map", in order); `"target_classes"`: the map's class names in order, or a number
  (default: the distinct targets in the order they first appear); optional `"unmapped"`
  (`"other"` or `"drop"`), `"other"` (the other class's name or index; default "other") and
  `"description"` (free text). Index keys are strings in JSON ("3"); a name always wins over an
  index reading of the same string. Example: `jaxfusion/datasets/class_maps/*.json`.
* CSV — one `source,target` row per network class, in the network's output order (an optional
  `source,target` header, blank lines and `#` comments are skipped); an empty target is
  unmapped. The target classes are the distinct targets in the order they first appear.

Shape legend: K_src source (network) classes, K_dst target (map) classes, M MC samples, `...`
any leading axes (pixels, frames).
"""

import csv
import difflib
import json
import os
import pathlib
import re
from typing import Any, Iterable, Mapping, Optional, Sequence, Union

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

# A class given by name or by index.
ClassRef = Union[str, int]

# Below this probability mass on the kept classes, `unmapped="drop"` gives the uniform
# distribution (and its largest variance): nothing is known about the kept classes there.
MIN_MASS = 1e-12

UNMAPPED_POLICIES = ("other", "drop")
_FILE_KEYS = ("source_classes", "target_classes", "map", "unmapped", "other", "description")


@struct.dataclass
class ClassMap:
  """A map from a network's K_src classes to a voxel map's K_dst classes (a pytree).

  Build one with `from_table` or `from_file`; `matrix` is a leaf (so a class map passes through
  `jax.jit` and `vmap` as an argument), the names and the policy are static.

  Attributes:
    matrix: `(K_src, K_dst) float32` 0/1; `matrix[i, j] = 1` when source class i goes to target
      class j. A row of zeros is a dropped class.
    source_classes: the K_src source class names, in the network's output order.
    target_classes: the K_dst target class names, in the map's order.
    renormalize: some source classes are dropped (`unmapped="drop"`): `remap` renormalises.
  """
  matrix: jax.Array                                                   # [K_src, K_dst] float32
  source_classes: tuple = struct.field(pytree_node=False)             # K_src str
  target_classes: tuple = struct.field(pytree_node=False)             # K_dst str
  renormalize: bool = struct.field(pytree_node=False, default=False)

  @property
  def num_source_classes(self) -> int:
    """K_src."""
    return len(self.source_classes)

  @property
  def num_target_classes(self) -> int:
    """K_dst."""
    return len(self.target_classes)

  @property
  def dropped_classes(self) -> tuple:
    """The names of the source classes with no target (empty unless `renormalize`)."""
    rows = np.asarray(self.matrix).sum(axis=1)
    return tuple(n for n, r in zip(self.source_classes, rows) if r == 0)

  # --- Building -------------------------------------------------------------------------------

  @classmethod
  def from_table(cls, table: Union[Mapping[ClassRef, Optional[ClassRef]],
                                   Iterable[tuple[ClassRef, Optional[ClassRef]]]], *,
                 source_classes: Union[Sequence[str], int],
                 target_classes: Union[Sequence[str], int],
                 unmapped: Optional[str] = None, other: ClassRef = "other") -> "ClassMap":
    """A class map from a table `source class → target class`.

    Args:
      table: a mapping (or `(source, target)` pairs) from a source class to a target class,
        each a name or an index; target None for unmapped. Source classes the table leaves out
        are unmapped too.
      source_classes: the network's class names in its output order, or their number K_src
        (names "0" ... "K_src−1").
      target_classes: the map's class names in order, or their number K_dst.
      unmapped: what happens to unmapped source classes: "other" sums them into the target
        class `other` (appended as the last target class when some class is unmapped and the
        targets have no such class); "drop" drops them and renormalises (`remap`); None
        (default): "other" when the target classes have the class `other`, and an error when
        some class is unmapped and they do not.
      other: the "other" target class, a name or an index.

    Returns:
      A `ClassMap`.

    Raises:
      ValueError: an unknown class name, an index out of range, a source class mapped twice,
        duplicate or empty class names, no source class with a target, or unmapped classes
        and no choice of what to do with them.
    """
    sources = _class_names(source_classes, "source")
    targets = list(_class_names(target_classes, "target"))
    if unmapped is not None and unmapped not in UNMAPPED_POLICIES:
      raise ValueError(f"unmapped must be one of {UNMAPPED_POLICIES} (or None); got "
                       f"{unmapped!r}")
    pairs = list(table.items()) if isinstance(table, Mapping) else list(table)
    dest = [None] * len(sources)
    seen = [False] * len(sources)
    for pair in pairs:
      if not isinstance(pair, (tuple, list)) or len(pair) != 2:
        raise ValueError(f"a class table entry must be a (source, target) pair; got {pair!r}")
      i = _resolve(pair[0], sources, "source")
      if seen[i]:
        raise ValueError(f"source class {sources[i]!r} is mapped twice")
      seen[i] = True
      dest[i] = None if pair[1] is None else _resolve(pair[1], targets, "target")
    missing = [sources[i] for i, d in enumerate(dest) if d is None]
    if missing and unmapped is None:
      has_other = (other in targets if isinstance(other, str) else
                   isinstance(other, (int, np.integer)) and 0 <= other < len(targets))
      if not has_other:
        shown = ", ".join(repr(n) for n in missing[:8]) + (", ..." if len(missing) > 8 else "")
        raise ValueError(
            f"{len(missing)} source class{'es' if len(missing) > 1 else ''} with no target "
            f"({shown}) and no {other!r} target class: choose unmapped 'drop' (drop them and "
            f"renormalise) or 'other' (sum them into an {other!r} class)")
      unmapped = "other"
    renormalize = False
    if missing and unmapped == "other":
      if isinstance(other, str) and other not in targets:
        if not other:
          raise ValueError("the 'other' class needs a name")
        targets.append(other)
      j = _resolve(other, targets, "target")
      dest = [j if d is None else d for d in dest]
    elif missing:
      renormalize = True
      if len(missing) == len(sources):
        raise ValueError("no source class has a target: every class would be dropped")
    matrix = np.zeros((len(sources), len(targets)), np.float32)
    for i, j in enumerate(dest):
      if j is not None:
        matrix[i, j] = 1.0
    return cls(jnp.asarray(matrix), sources, tuple(targets), renormalize)

  @classmethod
  def from_dict(cls, spec: Mapping[str, Any], *, unmapped: Optional[str] = None
                ) -> "ClassMap":
    """A class map from the JSON format's object (see the module docstring).

    Args:
      spec: dict with "map" and optional "source_classes", "target_classes", "unmapped",
        "other", "description".
      unmapped: overrides the dict's "unmapped" ("other" or "drop").

    Raises:
      ValueError: unknown keys, a malformed "map", or any error of `from_table`.
    """
    if not isinstance(spec, Mapping):
      raise ValueError(f"a class map is a JSON object; got {type(spec).__name__}")
    unknown = sorted(set(spec) - set(_FILE_KEYS))
    if unknown:
      raise ValueError(f"unknown class map keys {unknown}; the keys are {list(_FILE_KEYS)}")
    if "map" not in spec:
      raise ValueError("a class map needs a 'map' of source class → target class")
    table = spec["map"]
    if isinstance(table, Mapping):
      pairs = list(table.items())
    elif isinstance(table, list):
      pairs = [tuple(p) if isinstance(p, list) else p for p in table]
    else:
      raise ValueError("'map' must be an object {source: target} or a list of [source, "
                       f"target] pairs; got {type(table).__name__}")
    for pair in pairs:
      if not isinstance(pair, tuple) or len(pair) != 2:
        raise ValueError(f"a 'map' entry must be a [source, target] pair; got {pair!r}")
    sources = spec.get("source_classes", [p[0] for p in pairs])
    targets = spec.get("target_classes")
    if targets is None:
      targets = _first_appearance(pairs)
    return cls.from_table(pairs, source_classes=_names_or_count(sources, "source_classes"),
                          target_classes=_names_or_count(targets, "target_classes"),
                          unmapped=spec.get("unmapped") if unmapped is None else unmapped,
                          other=spec.get("other", "other"))

  @classmethod
  def from_file(cls, path: Union[str, os.PathLike], *, unmapped: Optional[str] = None
                ) -> "ClassMap":
    """Reads a class map from a `.json` or `.csv` file (format: the module docstring).

    Args:
      path: the file.
      unmapped: overrides the file's choice for unmapped classes ("other" or "drop").

    Raises:
      FileNotFoundError: no such file.
      ValueError: another suffix, a malformed file (with its line for CSV), or any error of
        `from_table`; the message starts with the path.
    """
    path = pathlib.Path(path)
    if path.suffix.lower() not in (".json", ".csv"):
      raise ValueError(f"{path}: a class map is a .json or .csv file")
    if not path.is_file():
      raise FileNotFoundError(f"no class map file {path}")
    try:
      try:
        text = path.read_text(encoding="utf-8")
      except UnicodeDecodeError as e:
        raise ValueError(f"not a text file ({e})") from None
      if path.suffix.lower() == ".json":
        try:
          spec = json.loads(text, object_pairs_hook=_no_duplicate_keys)
        except json.JSONDecodeError as e:
          raise ValueError(f"not valid JSON: {e}") from None
        return cls.from_dict(spec, unmapped=unmapped)
      pairs = _read_csv(text)
      targets = _first_appearance(pairs)
      return cls.from_table(pairs, source_classes=[p[0] for p in pairs],
                            target_classes=targets, unmapped=unmapped)
    except (ValueError, csv.Error, RecursionError) as e:
      raise ValueError(f"{path}: {e}") from None

  def to_dict(self) -> dict:
    """The JSON format's object (`from_dict` reads it back to the same map)."""
    matrix = np.asarray(self.matrix)
    table = {}
    for i, name in enumerate(self.source_classes):
      hits = np.flatnonzero(matrix[i])
      table[name] = self.target_classes[int(hits[0])] if hits.size else None
    return {"source_classes": list(self.source_classes),
            "target_classes": list(self.target_classes), "map": table,
            "unmapped": "drop" if self.renormalize else "other"}

  # --- Remapping ------------------------------------------------------------------------------

  def remap(self, probs: jax.Array, var: Optional[jax.Array] = None
            ) -> tuple[jax.Array, Optional[jax.Array]]:
    """Remaps a frame's MC moments to the target classes (pure; jittable; any leading axes).

    `p' = p A` (many-to-one classes summed); `var' = min(var A, p'(1 − p'))`, the variance of a
    sum taken as the sum of the variances (independence assumed, see the module docstring).
    With dropped classes, `p' ← p'/s` for the kept mass `s` (uniform where `s ≤ MIN_MASS`) and
    `var A ← var A / s²` (delta method, s treated as a constant) before the clip.

    Args:
      probs: `(..., K_src)` float class probabilities.
      var: `(..., K_src)` float per-class variance, or None.

    Returns:
      `(probs', var')`: `(..., K_dst) float32`, var' None when var is.

    Raises:
      ValueError: the last axis is not K_src, or var's shape is not probs'.
    """
    probs = self._check_input(probs, "probabilities")
    if var is None:
      return _remap_probs(self, probs), None
    var = self._check_input(var, "variances")
    if var.shape != probs.shape:
      raise ValueError(f"variances {var.shape} must have the probabilities' shape "
                       f"{probs.shape}")
    return _remap_moments(self, probs, var)

  def remap_samples(self, samples: jax.Array) -> jax.Array:
    """Remaps class-probability samples (pure; jittable): then `mc_moments` is exact.

    Each sample is summed over many-to-one classes and, with dropped classes, renormalised
    (uniform where its kept mass is `≤ MIN_MASS`), so the moments of the result are the
    moments of the remapped distribution, with no independence assumption.

    Args:
      samples: `(M, H, W, K_src)` float samples (any leading axes work).

    Returns:
      `(M, H, W, K_dst) float32` samples, for `sources.mc_moments`.

    Raises:
      ValueError: the last axis is not K_src.
    """
    return _remap_probs(self, self._check_input(samples, "samples"))

  def _check_input(self, x, what: str) -> jax.Array:
    if not hasattr(x, "dtype"):
      x = np.asarray(x)
    shape = np.shape(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
      raise ValueError(f"the class map takes float {what}; got dtype {x.dtype}")
    if len(shape) < 1 or shape[-1] != self.num_source_classes:
      raise ValueError(f"the class map has {self.num_source_classes} source classes but the "
                       f"{what} have {shape[-1] if shape else 0} (shape {tuple(shape)})")
    return x


# The arithmetic of `remap` and `remap_samples`, compiled once per class map structure and input
# shape, so that a plain call runs one fused program rather than op by op; under a caller's
# transformation they trace inline.
@jax.jit
def _remap_probs(cm: ClassMap, probs: jax.Array) -> jax.Array:
  mass = _apply(probs.astype(jnp.float32), cm.matrix)
  return _renormalize(mass)[0] if cm.renormalize else mass


@jax.jit
def _remap_moments(cm: ClassMap, probs: jax.Array, var: jax.Array
                   ) -> tuple[jax.Array, jax.Array]:
  mass = _apply(probs.astype(jnp.float32), cm.matrix)
  probs_out = mass
  if cm.renormalize:
    probs_out, total, ok = _renormalize(mass)
  var_out = _apply(var.astype(jnp.float32), cm.matrix)
  if cm.renormalize:
    safe_total = jnp.where(ok, total, 1.0)
    var_out = jnp.where(ok, var_out / (safe_total * safe_total), 1.0)
  bound = jnp.maximum(probs_out * (1.0 - probs_out), 0.0)
  return probs_out, jnp.clip(var_out, 0.0, bound)


def _apply(x, matrix):
  # Full float32 precision: on GPUs a default-precision matmul may round through TF32.
  return jnp.matmul(x, matrix, precision=jax.lax.Precision.HIGHEST)


def _renormalize(mass):
  """`(mass / s, s, s > MIN_MASS)` over the last axis; uniform where the mass is too small
  (double `where`, so the gradient stays finite)."""
  total = jnp.sum(mass, axis=-1, keepdims=True)
  ok = total > MIN_MASS
  safe_total = jnp.where(ok, total, 1.0)
  return jnp.where(ok, mass / safe_total, 1.0 / mass.shape[-1]), total, ok


def _class_names(classes, role: str) -> tuple:
  """Class names from a list of names or a count."""
  if isinstance(classes, (bool, np.bool_)):
    raise ValueError(f"{role} classes must be a list of names or a count; got {classes!r}")
  if isinstance(classes, (int, np.integer)):
    if classes < 1:
      raise ValueError(f"there must be at least one {role} class; got {classes}")
    return tuple(str(i) for i in range(int(classes)))
  if isinstance(classes, str):
    raise ValueError(f"{role} classes must be a list of names, not one string {classes!r}")
  names = tuple(classes)
  if not names:
    raise ValueError(f"there must be at least one {role} class")
  for name in names:
    if not isinstance(name, str) or not name.strip():
      raise ValueError(f"{role} class names must be non-empty strings; got {name!r}")
  dupes = sorted({n for n in names if names.count(n) > 1})
  if dupes:
    raise ValueError(f"duplicate {role} class names: {dupes}")
  return names


def _resolve(ref, names, role: str) -> int:
  """The index of a class given by name or index (an index may be a digit string)."""
  if isinstance(ref, (bool, np.bool_)):
    raise ValueError(f"a {role} class is a name or an index; got {ref!r}")
  if isinstance(ref, (int, np.integer)):
    if not 0 <= ref < len(names):
      raise ValueError(f"{role} class index {int(ref)} is out of range: there are "
                       f"{len(names)} {role} classes (0 to {len(names) - 1})")
    return int(ref)
  if isinstance(ref, str):
    if ref in names:
      return list(names).index(ref)
    if re.fullmatch(r"\s*[+-]?\d+\s*", ref):
      return _resolve(int(ref), names, role)
    close = difflib.get_close_matches(ref, names, n=1)
    hint = f"; did you mean {close[0]!r}?" if close else ""
    shown = ", ".join(repr(n) for n in names[:10]) + (
        f", ... ({len(names)} in all)" if len(names) > 10 else "")
    raise ValueError(f"unknown {role} class {ref!r}{hint} (the {role} classes: {shown})")
  raise ValueError(f"a {role} class is a name or an index; got {ref!r}")


def _names_or_count(value, key: str):
  if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
    return int(value)
  if isinstance(value, (list, tuple)):
    return list(value)
  raise ValueError(f"'{key}' must be a list of class names or a number; got {value!r}")


def _first_appearance(pairs) -> list:
  """The distinct target names of `(source, target)` pairs, in the order they first appear."""
  targets = []
  for _, target in pairs:
    if target is None:
      continue
    if not isinstance(target, str):
      raise ValueError(f"target {target!r} is an index: give 'target_classes' to index into")
    if target not in targets:
      targets.append(target)
  return targets


def _no_duplicate_keys(pairs):
  keys = [k for k, _ in pairs]
  dupes = sorted({k for k in keys if keys.count(k) > 1})
  if dupes:
    raise ValueError(f"duplicate JSON keys {dupes} (a source class mapped twice?)")
  return dict(pairs)


def _read_csv(text: str) -> list:
  """`(source, target or None)` pairs of a CSV class map, checked row by row."""
  pairs, sources, header_allowed = [], {}, True
  for line, row in enumerate(csv.reader(text.splitlines()), start=1):
    cells = [c.strip() for c in row]
    if not cells or not any(cells) or cells[0].startswith("#"):
      continue
    if header_allowed and [c.lower() for c in cells] == ["source", "target"]:
      header_allowed = False
      continue
    header_allowed = False
    if len(cells) != 2:
      raise ValueError(f"line {line}: a row is 'source,target' (empty target: unmapped); got "
                       f"{len(cells)} fields")
    source, target = cells
    if not source:
      raise ValueError(f"line {line}: empty source class")
    if source in sources:
      raise ValueError(f"line {line}: source class {source!r} is mapped twice (first on line "
                       f"{sources[source]})")
    sources[source] = line
    pairs.append((source, target or None))
  if not pairs:
    raise ValueError("no 'source,target' rows")
  return pairs

