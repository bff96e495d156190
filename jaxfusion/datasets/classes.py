"""Class names, colour tables and the NYU40 → 12-class mapping used by the paper.

Two label sets are used:

* The synthetic world (the paper's AirSim "Office"/"House" scenes): 7 classes,
  `CLASS_NAMES`, with the paper's colours `CLASS_COLORS`.
* ScanNet (the paper's real sequences): 12 classes, `SCANNET_CLASS_NAMES`, with
  `SCANNET_COLORS`. ScanNet's `label-filt/*.png` hold NYU40 ids; `NYU40_TO_SCANNET12`
  maps them. NYU40 ids with no counterpart among the 12 classes — `wall` (1), which the
  paper's table leaves out, and `0` (unannotated) — become `IGNORE_LABEL`.

`IGNORE_LABEL = -1` marks pixels that carry no ground truth: they are never fused into GT
voxel labels and should be excluded from metrics.

Class maps (`jaxfusion.ClassMap`) for a network that predicts NYU40 classes: `nyu40_class_map`
builds NYU40 → the paper's 12 classes (`NYU40_TABLE`) or → the ScanNet benchmark's 20 classes
(`SCANNET20_TABLE`, `SCANNET20_CLASS_NAMES`); the classes without a target are dropped, as the
ScanNet loader ignores their labels. The same maps ship as files for `jaxfusion run --class-map`:
`class_map_path("nyu40_to_scannet12")`, `class_map_path("nyu40_to_scannet20")`.
"""

import pathlib

import numpy as np

from jaxfusion.classmap import ClassMap

IGNORE_LABEL = -1

CLASS_NAMES = ("background", "bottle", "chair", "table", "plant", "sofa", "tv")
BACKGROUND, BOTTLE, CHAIR, TABLE, PLANT, SOFA, TV = range(7)


def _hex_table(hex_colors) -> np.ndarray:
  """`(K, 3) uint8` RGB table from `"RRGGBB"` strings."""
  return np.array([[int(h[i:i + 2], 16) for i in (0, 2, 4)] for h in hex_colors], np.uint8)


CLASS_COLORS = _hex_table(("343434", "604BA4", "FE0000", "F56B00", "009901", "34FF34", "00009B"))

SCANNET_CLASS_NAMES = ("bed", "ceiling", "chair", "floor", "furniture", "objects", "picture",
                       "sofa", "table", "tv", "door", "window")
SCANNET_COLORS = _hex_table(("FFBB78", "4E47B7", "BCBD22", "98DF8A", "8C9965", "FF7F0E",
                             "A1AB1B", "BEE140", "CEBE3B", "73B0C3", "996C06", "F7B6D2"))

# NYU40 id → (NYU40 name, 12-class name or None for IGNORE_LABEL). The grouping follows the
# standard NYU-v2 40 → 13 table (Couprie et al., used by SemanticFusion), adapted to the paper's
# 12 classes: `door` is its own class, `books` joins `objects`, and `wall` is ignored.
NYU40_TABLE = (
    (0, "unannotated", None),
    (1, "wall", None),
    (2, "floor", "floor"),
    (3, "cabinet", "furniture"),
    (4, "bed", "bed"),
    (5, "chair", "chair"),
    (6, "sofa", "sofa"),
    (7, "table", "table"),
    (8, "door", "door"),
    (9, "window", "window"),
    (10, "bookshelf", "furniture"),
    (11, "picture", "picture"),
    (12, "counter", "furniture"),
    (13, "blinds", "window"),
    (14, "desk", "table"),
    (15, "shelves", "furniture"),
    (16, "curtain", "window"),
    (17, "dresser", "furniture"),
    (18, "pillow", "objects"),
    (19, "mirror", "objects"),
    (20, "floor mat", "floor"),
    (21, "clothes", "objects"),
    (22, "ceiling", "ceiling"),
    (23, "books", "objects"),
    (24, "refrigerator", "furniture"),
    (25, "television", "tv"),
    (26, "paper", "objects"),
    (27, "towel", "objects"),
    (28, "shower curtain", "objects"),
    (29, "box", "objects"),
    (30, "whiteboard", "objects"),
    (31, "person", "objects"),
    (32, "night stand", "furniture"),
    (33, "toilet", "objects"),
    (34, "sink", "objects"),
    (35, "lamp", "objects"),
    (36, "bathtub", "objects"),
    (37, "bag", "objects"),
    (38, "otherstructure", "objects"),
    (39, "otherfurniture", "furniture"),
    (40, "otherprop", "objects"),
)


def nyu40_to_scannet12_lut() -> np.ndarray:
  """Lookup table from NYU40 ids to 12-class indices.

  Returns:
    `(256,) int32`: entry `i` is the index into `SCANNET_CLASS_NAMES` of NYU40 id `i`, or
    `IGNORE_LABEL` for ids without a class (0, 1 = wall, and anything above 40).
  """
  lut = np.full((256,), IGNORE_LABEL, np.int32)
  for nyu_id, _, name in NYU40_TABLE:
    if name is not None:
      lut[nyu_id] = SCANNET_CLASS_NAMES.index(name)
  return lut


NYU40_TO_SCANNET12 = nyu40_to_scannet12_lut()

# The NYU40 names by id (index 0 is "unannotated").
NYU40_CLASS_NAMES = tuple(name for _, name, _ in NYU40_TABLE)

# The ScanNet benchmark's 20 classes: (NYU40 id, name), in the benchmark's order
# (`VALID_CLASS_IDS` of ScanNet's evaluation scripts). The other NYU40 ids are not scored.
SCANNET20_TABLE = (
    (1, "wall"), (2, "floor"), (3, "cabinet"), (4, "bed"), (5, "chair"), (6, "sofa"),
    (7, "table"), (8, "door"), (9, "window"), (10, "bookshelf"), (11, "picture"),
    (12, "counter"), (14, "desk"), (16, "curtain"), (24, "refrigerator"),
    (28, "shower curtain"), (33, "toilet"), (34, "sink"), (36, "bathtub"),
    (39, "otherfurniture"),
)
SCANNET20_CLASS_NAMES = tuple(name for _, name in SCANNET20_TABLE)


def nyu40_to_scannet20_lut() -> np.ndarray:
  """Lookup table from NYU40 ids to the benchmark's 20-class indices.

  Returns:
    `(256,) int32`: entry `i` is the index into `SCANNET20_CLASS_NAMES` of NYU40 id `i`, or
    `IGNORE_LABEL` for the ids the benchmark does not score.
  """
  lut = np.full((256,), IGNORE_LABEL, np.int32)
  for index, (nyu_id, _) in enumerate(SCANNET20_TABLE):
    lut[nyu_id] = index
  return lut


NYU40_TO_SCANNET20 = nyu40_to_scannet20_lut()

# The embedded world's classes as NYU40 ids, for writing it in ScanNet's layout (`label-filt/`
# PNGs and the labelled mesh hold NYU40 ids). NYU40 has no bottle and no plant: they take the
# two "other" ids that no other embedded class uses, so that the table inverts exactly
# (`LABEL_SPACES["embedded"]`). The embedded background (walls, floor, ceiling) is `wall`.
EMBEDDED_TO_NYU40 = np.array([1, 40, 5, 7, 38, 6, 25], np.int32)


def nyu40_to_embedded_lut() -> np.ndarray:
  """`(256,) int32` lookup from NYU40 ids to the embedded world's classes (the inverse of
  `EMBEDDED_TO_NYU40`; every other id is `IGNORE_LABEL`)."""
  lut = np.full((256,), IGNORE_LABEL, np.int32)
  lut[EMBEDDED_TO_NYU40] = np.arange(len(CLASS_NAMES), dtype=np.int32)
  return lut


def nyu40_identity_lut() -> np.ndarray:
  """`(256,) int32` lookup that keeps NYU40 ids 1 … 40 as classes 0 … 39 (0 = unannotated and
  ids above 40 are `IGNORE_LABEL`)."""
  lut = np.full((256,), IGNORE_LABEL, np.int32)
  lut[1:41] = np.arange(40, dtype=np.int32)
  return lut


# The label spaces a dataset's GT can be read into: name → (class names, NYU40 id → class
# lookup `(256,) int32`, IGNORE_LABEL where an id has no class). `scannet12` is the paper's
# (and the ScanNet reader's default), `scannet20` the ScanNet benchmark's, `nyu40` the 40 NYU
# classes themselves, `embedded` the embedded world's 7 (as `EMBEDDED_TO_NYU40` writes them).
LABEL_SPACES = {
    "scannet12": (SCANNET_CLASS_NAMES, NYU40_TO_SCANNET12),
    "scannet20": (SCANNET20_CLASS_NAMES, NYU40_TO_SCANNET20),
    "nyu40": (NYU40_CLASS_NAMES[1:], nyu40_identity_lut()),
    "embedded": (CLASS_NAMES, nyu40_to_embedded_lut()),
}


def label_space(name: str) -> tuple:
  """`(class_names, lut)` of a label space of `LABEL_SPACES`; raises ValueError naming them."""
  if name not in LABEL_SPACES:
    raise ValueError(f"unknown label space {name!r}; the label spaces are "
                     f"{', '.join(LABEL_SPACES)}")
  names, lut = LABEL_SPACES[name]
  return tuple(names), lut


# The class maps shipped as files (`jaxfusion/datasets/class_maps/NAME.json`).
CLASS_MAPS = ("nyu40_to_scannet12", "nyu40_to_scannet20")


def nyu40_class_map(target: str = "scannet12", *, unannotated: bool = True) -> ClassMap:
  """A class map from a network's NYU40 classes to the paper's 12 or the benchmark's 20.

  NYU40 classes without a target (for 12: unannotated and wall; for 20: unannotated and the
  20 unscored ids) are dropped and the rest renormalised (`unmapped="drop"`), as the ScanNet
  loader ignores those labels (`IGNORE_LABEL`).

  Args:
    target: "scannet12" (`SCANNET_CLASS_NAMES`, by `NYU40_TABLE`) or "scannet20"
      (`SCANNET20_CLASS_NAMES`).
    unannotated: the network has 41 outputs, index = NYU40 id, 0 = unannotated (default);
      False: 40 outputs, ids 1 ... 40 at indices 0 ... 39.

  Returns:
    A `ClassMap` with the NYU40 names as source classes.
  """
  if target == "scannet12":
    table = {nyu_id: name for nyu_id, _, name in NYU40_TABLE}
    targets = SCANNET_CLASS_NAMES
  elif target == "scannet20":
    table = {nyu_id: name for nyu_id, name in SCANNET20_TABLE}
    targets = SCANNET20_CLASS_NAMES
  else:
    raise ValueError(f"target must be 'scannet12' or 'scannet20'; got {target!r}")
  first = 0 if unannotated else 1
  table = {NYU40_CLASS_NAMES[i]: table.get(i) for i in range(first, len(NYU40_CLASS_NAMES))}
  return ClassMap.from_table(table, source_classes=NYU40_CLASS_NAMES[first:],
                             target_classes=targets, unmapped="drop")


def class_map_path(name: str) -> pathlib.Path:
  """The shipped class map file `name` (one of `CLASS_MAPS`), for `ClassMap.from_file`."""
  if name not in CLASS_MAPS:
    raise ValueError(f"no shipped class map {name!r}; the shipped ones are {list(CLASS_MAPS)}")
  return pathlib.Path(__file__).resolve().parent / "class_maps" / f"{name}.json"


def colorize(labels: np.ndarray, colors: np.ndarray) -> np.ndarray:
  """Maps a label image to colours.

  Args:
    labels: `(..., ) int` class indices; `IGNORE_LABEL` (or any out-of-range value) is black.
    colors: `(K, 3) uint8` colour table.

  Returns:
    `(..., 3) uint8` RGB image.
  """
  labels = np.asarray(labels)
  colors = np.asarray(colors, np.uint8)
  valid = (labels >= 0) & (labels < len(colors))
  out = colors[np.where(valid, labels, 0)]
  out[~valid] = 0
  return out


def palette(classes) -> np.ndarray:
  """`(K, 3) uint8` colours for a map's classes: the project's table for its class lists (the
  embedded world's, ScanNet's 12), else distinct colours (`io.default_palette`).

  Args:
    classes: the class names, or just K (a table is then picked by its length).
  """
  names = None if isinstance(classes, (int, np.integer)) else tuple(classes)
  count = int(classes) if names is None else len(names)
  for table_names, colors in ((CLASS_NAMES, CLASS_COLORS),
                              (SCANNET_CLASS_NAMES, SCANNET_COLORS)):
    if (names == tuple(table_names)) if names is not None else count == len(table_names):
      return np.asarray(colors, np.uint8)
  from jaxfusion import io  # pylint: disable=import-outside-toplevel  (io imports the engine)
  return io.default_palette(count)
