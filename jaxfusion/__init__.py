"""jaxfusion: robust Bayesian semantic voxel mapping in JAX.

The pipeline: camera geometry → spatial hash → map state → fusion rules → `fuse_frame` →
readout → metrics, with per-pixel context features of a frame (`context`) for the rules that
read them; beside the semantics, a geometry layer (`tsdf`, a TSDF fused in the same
call) and its meshes (`mesh`, marching cubes). Batches, sweeps and tuning build on it
(`batch`, `tune`); the synthetic world and real-data readers live in `jaxfusion.datasets`, the
simulated front ends (independent or view-dependent errors) in `jaxfusion.simulation`, the
analyses of a front end's pixel observations of GT voxels in `jaxfusion.observations`, map files
in `jaxfusion.io`; free-space clearing (`free_space`) and exact de-integration and
re-integration of frames (`deintegration`) for a world or poses that change. The equations are in docs/equations.md.

This package is the library. The application (commands, studies, figures, the viewer) is
`jaxfusion.lab`, which this package never imports.

Its names load on first use (a module `__getattr__`, as SPEC 1's lazy loading): `import
jaxfusion` imports no JAX, so a command can re-execute itself before JAX is loaded
(`jaxfusion.lab.hugepages`), and `jf.fuse_frame`, `from jaxfusion import Mapper` or
`jf.tsdf.TSDFConfig` import what they name then.
"""

import importlib
import importlib.util
from typing import TYPE_CHECKING

# The submodules offered as attributes, and the names re-exported from submodules.
_SUBMODULES = (
    "batch", "context", "datasets", "deintegration", "distributed", "free_space", "io", "learn",
    "mesh", "metrics", "rules", "sources", "tsdf", "tune",
)
_EXPORTS = {
    "fuse_batch": "batch",
    "fuse_sweep": "batch",
    "make_mesh": "batch",
    "rule_grid": "batch",
    "stack_sequences": "batch",
    "Camera": "camera",
    "ClassMap": "classmap",
    "reintegrate": "deintegration",
    "unfuse_frame": "deintegration",
    "FreeSpaceConfig": "free_space",
    "Frame": "fusion",
    "fuse_frame": "fusion",
    "fuse_sequence": "fusion",
    "EMPTY": "hashing",
    "Mapper": "mapper",
    "Mesh": "mesh",
    "extract_mesh": "mesh",
    "label_mesh": "mesh",
    "mesh_by_class": "mesh",
    "QueryResult": "readout",
    "query": "readout",
    "read_map": "readout",
    "voxel_posteriors": "readout",
    "FusionRule": "rules",
    "mc_moments": "sources",
    "MapFullWarning": "state",
    "MapState": "state",
    "capacity_for": "state",
    "grow_map": "state",
    "init_map": "state",
    "map_stats": "state",
    "calibration_loss": "tune",
    "sweep_beta": "tune",
    "TSDFConfig": "tsdf",
    "TSDFState": "tsdf",
    "init_tsdf": "tsdf",
    "tune_hparams": "tune",
}

__version__ = "0.1.0"

__all__ = sorted([
    "Camera", "ClassMap", "EMPTY", "Frame", "FreeSpaceConfig", "FusionRule", "MapFullWarning", "MapState", "Mapper",
    "Mesh", "QueryResult", "TSDFConfig", "TSDFState", "extract_mesh", "init_tsdf", "label_mesh",
    "mesh",
    "mesh_by_class", "tsdf", "batch", "context", "calibration_loss", "capacity_for", "datasets",
    "fuse_batch",
    "fuse_frame", "fuse_sequence", "fuse_sweep", "grow_map", "init_map", "io", "learn",
    "make_mesh", "map_stats", "mc_moments", "metrics", "query", "read_map", "rule_grid", "rules",
    "sources", "stack_sequences", "sweep_beta", "tune", "tune_hparams", "voxel_posteriors",
    "deintegration", "free_space", "reintegrate", "unfuse_frame",
])


def __getattr__(name: str):
  """Loads a re-exported name or a submodule on first use (and keeps it)."""
  if name in _EXPORTS:
    value = getattr(importlib.import_module(f"{__name__}.{_EXPORTS[name]}"), name)
  elif not name.startswith("_") and importlib.util.find_spec(f"{__name__}.{name}") is not None:
    value = importlib.import_module(f"{__name__}.{name}")
  else:
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
  globals()[name] = value
  return value


def __dir__():
  return sorted(set(globals()) | set(__all__) | set(_SUBMODULES))


if TYPE_CHECKING:   # what the names are, for type checkers and editors
  from jaxfusion import batch
  from jaxfusion import context
  from jaxfusion import datasets
  from jaxfusion import deintegration
  from jaxfusion import distributed
  from jaxfusion import free_space
  from jaxfusion import io
  from jaxfusion import learn
  from jaxfusion import mesh
  from jaxfusion import metrics
  from jaxfusion import rules
  from jaxfusion import sources
  from jaxfusion import tsdf
  from jaxfusion import tune
  from jaxfusion.batch import fuse_batch
  from jaxfusion.batch import fuse_sweep
  from jaxfusion.batch import make_mesh
  from jaxfusion.batch import rule_grid
  from jaxfusion.batch import stack_sequences
  from jaxfusion.camera import Camera
  from jaxfusion.classmap import ClassMap
  from jaxfusion.deintegration import reintegrate
  from jaxfusion.deintegration import unfuse_frame
  from jaxfusion.free_space import FreeSpaceConfig
  from jaxfusion.fusion import Frame
  from jaxfusion.fusion import fuse_frame
  from jaxfusion.fusion import fuse_sequence
  from jaxfusion.hashing import EMPTY
  from jaxfusion.mapper import Mapper
  from jaxfusion.mesh import Mesh
  from jaxfusion.mesh import extract_mesh
  from jaxfusion.mesh import label_mesh
  from jaxfusion.mesh import mesh_by_class
  from jaxfusion.readout import QueryResult
  from jaxfusion.readout import query
  from jaxfusion.readout import read_map
  from jaxfusion.readout import voxel_posteriors
  from jaxfusion.rules import FusionRule
  from jaxfusion.sources import mc_moments
  from jaxfusion.state import MapFullWarning
  from jaxfusion.state import MapState
  from jaxfusion.state import capacity_for
  from jaxfusion.state import grow_map
  from jaxfusion.state import init_map
  from jaxfusion.state import map_stats
  from jaxfusion.tune import calibration_loss
  from jaxfusion.tune import sweep_beta
  from jaxfusion.tsdf import TSDFConfig
  from jaxfusion.tsdf import TSDFState
  from jaxfusion.tsdf import init_tsdf
  from jaxfusion.tune import tune_hparams
