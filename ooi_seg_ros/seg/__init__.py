"""Segmentation of the object of interest: SfM cloud -> OOI cloud -> mesh -> per-view masks.

``segment(capture, cloud, make_config("ours" | "paper"))`` runs the whole pipeline; each
stage lives in its own module with its own config dataclass (density, floor, noise, mesh,
masks, plus the improved mode's roi and refine).
"""

from .pipeline import (METHODS, SegmentationConfig, SegmentationResult, make_config,  # noqa
                       segment)
