"""jaxfusion: robust Bayesian semantic voxel mapping in JAX.

The pipeline: camera geometry → spatial hash → map state → fusion rules → `fuse_frame` →
readout. See README.md for a usage example and SPEC.md for the equations.
"""

from jaxfusion import rules
from jaxfusion.camera import Camera
from jaxfusion.fusion import Frame
from jaxfusion.fusion import fuse_frame
from jaxfusion.fusion import fuse_sequence
from jaxfusion.hashing import EMPTY
from jaxfusion.readout import read_map
from jaxfusion.readout import voxel_posteriors
from jaxfusion.rules import FusionRule
from jaxfusion.sources import mc_moments
from jaxfusion.state import MapFullWarning
from jaxfusion.state import MapState
from jaxfusion.state import init_map
from jaxfusion.state import map_stats

__version__ = "0.1.0"

__all__ = sorted([
    "Camera", "EMPTY", "Frame", "FusionRule", "MapFullWarning", "MapState", "fuse_frame",
    "fuse_sequence", "init_map", "map_stats", "mc_moments", "read_map", "rules",
    "voxel_posteriors",
])
