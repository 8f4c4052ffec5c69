"""The paper's baselines, numpy + scipy + trimesh + scikit-image (no torch): reprojection and space carving.

`carve_hull` is also the fast reconstruction's initial hull and constraint.
"""

from .returns import DEFAULT_THRESHOLD, FirstReturns, first_returns
from .space_carving import CarveResult, carve_hull

__all__ = ["DEFAULT_THRESHOLD", "FirstReturns", "first_returns", "CarveResult", "carve_hull"]
