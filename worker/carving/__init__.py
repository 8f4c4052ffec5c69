"""What the histograms show without a model, numpy only: each histogram's first return, and the space carving
built on them (voxels a zone saw empty are removed).

Both the paper's baselines (`worker.baselines`) and the `fast` reconstruction's hull (`worker.recon.fast`) stand on
it; it imports neither.
"""

from .returns import DEFAULT_THRESHOLD, FirstReturns, first_returns
from .space_carving import CarveResult, carve_hull, carve_scene

__all__ = ["DEFAULT_THRESHOLD", "FirstReturns", "first_returns", "CarveResult", "carve_hull", "carve_scene"]
