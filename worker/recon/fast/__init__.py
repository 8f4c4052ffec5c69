"""The `fast` reconstruction preset: an explicit SDF grid started and bounded by the space-carving hull.

Read it from `model.py` down: `FastModel._step` is the loop and lists what runs when. The core: `config` (the
preset's dataclasses), `problem` (what is fitted, built from a SceneData: counts, candidate rays, carved hull, table
plane), `grid_field` (trilinear SDF grid, refined 2x), `hull` (the carved hull as start and bound), `sampler`
(hull-hitting rays, samples around the zero crossing), `render` (NeuS-style returns with fixed sharpness),
`regularizers` (finite-difference Eikonal and smoothness), `optim` (a small Adam), `mesh` and `grid_ops` (marching
cubes with cleaning; node heights, cavities, the space under overhangs), `evidence` (measured against expected
photons at the returns). Every mechanism beyond that is a part, one module each under `parts/`, with its config
beside it (`parts/__init__.py` lists them in the order their hooks run).
"""
