"""Datasets: the embedded synthetic world and readers for real RGB-D layouts.

Every source yields the same interface, an `RGBDSequence` of `RGBDFrame`s.
"""

from jaxfusion.datasets.classes import (CLASS_COLORS, CLASS_NAMES, IGNORE_LABEL,
                                        NYU40_TO_SCANNET12, SCANNET_CLASS_NAMES, SCANNET_COLORS)
from jaxfusion.datasets.sequence import RGBDFrame, RGBDSequence, Sequence, load_sequence
from jaxfusion.datasets.synthetic import list_sequences, make_sequence, sample_views

__all__ = [
    "CLASS_COLORS",
    "CLASS_NAMES",
    "IGNORE_LABEL",
    "NYU40_TO_SCANNET12",
    "RGBDFrame",
    "RGBDSequence",
    "SCANNET_CLASS_NAMES",
    "SCANNET_COLORS",
    "Sequence",
    "list_sequences",
    "load_sequence",
    "make_sequence",
    "sample_views",
]
