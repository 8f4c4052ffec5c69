"""The paper's baselines, numpy + scipy + trimesh + scikit-image (no torch): reprojection and space carving.

Both stand on the first returns and the carving of `worker.carving`, which the `fast` reconstruction's hull shares.
"""
