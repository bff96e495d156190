"""Datasets: the embedded synthetic world and readers for real RGB-D layouts.

Every source yields the same interface, an `RGBDSequence` of `RGBDFrame`s:

* `synthetic.make_sequence(env, trajectory, ...)` / `synthetic.sample_views(...)` — the
  procedural "office"/"house" world with a train/test appearance domain gap, seen through the
  view-dependent camera model `SensingConfig` (`SensingConfig.off()`: the plain sensor);
* `load_scannet(path)` — ScanNet exports (NYU40 → 12 classes, see `classes.NYU40_TABLE`);
* `load_tum(path)` — TUM RGB-D folders;
* `middlebury_frame()` — one real RGB-D frame from scikit-image's Middlebury pair;
* `gt_voxel_labels(sequence)` — majority GT label per voxel, fused by the engine;
* `load_spec("office:0" | "scannet:PATH" | "tum:PATH" | "saved:PATH")` — any of them by name
  (`specs`: the one sequence syntax of every command).
"""

from jaxfusion.datasets.classes import CLASS_COLORS
from jaxfusion.datasets.classes import CLASS_NAMES
from jaxfusion.datasets.classes import IGNORE_LABEL
from jaxfusion.datasets.classes import NYU40_TO_SCANNET12
from jaxfusion.datasets.classes import SCANNET_CLASS_NAMES
from jaxfusion.datasets.classes import SCANNET_COLORS
from jaxfusion.datasets.classes import palette
from jaxfusion.datasets.ground_truth import gt_voxel_labels
from jaxfusion.datasets.middlebury import middlebury_frame
from jaxfusion.datasets.preview import render_preview
from jaxfusion.datasets.scannet import load_scannet
from jaxfusion.datasets.camera_model import SensingConfig
from jaxfusion.datasets.sequence import RGBDFrame
from jaxfusion.datasets.sequence import RGBDSequence
from jaxfusion.datasets.sequence import load_sequence
from jaxfusion.datasets.specs import SequenceSpec
from jaxfusion.datasets.specs import load_spec
from jaxfusion.datasets.specs import parse_spec
from jaxfusion.datasets.specs import unit_name
from jaxfusion.datasets.synthetic import list_sequences
from jaxfusion.datasets.synthetic import make_sequence
from jaxfusion.datasets.synthetic import sample_views
from jaxfusion.datasets.tum import load_tum

__all__ = sorted([
    "CLASS_COLORS", "CLASS_NAMES", "IGNORE_LABEL", "NYU40_TO_SCANNET12", "RGBDFrame",
    "RGBDSequence", "SCANNET_CLASS_NAMES", "SCANNET_COLORS", "SensingConfig", "SequenceSpec",
    "gt_voxel_labels",
    "list_sequences", "load_scannet", "load_sequence", "load_spec", "load_tum", "make_sequence",
    "middlebury_frame", "palette", "parse_spec", "render_preview", "sample_views", "unit_name",
])


def __getattr__(name):
  # `datasets.Sequence` was the old name of `RGBDSequence` (it shadowed `typing.Sequence` in a
  # star import); it still resolves, with a warning.
  if name == "Sequence":
    import warnings  # pylint: disable=import-outside-toplevel
    warnings.warn("jaxfusion.datasets.Sequence is RGBDSequence; use that name",
                  DeprecationWarning, stacklevel=2)
    return RGBDSequence
  raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
