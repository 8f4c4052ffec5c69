"""The `fast` reconstruction preset: an explicit SDF grid started and bounded by the space-carving hull.

Parts: `config` (the preset's dataclasses), `grid_field` (trilinear SDF grid, coarse-to-fine), `hull` (carved hull as
start and constraint), `sampler` (hull-hitting rays, samples around the zero crossing), `render` (NeuS-style returns
with fixed sharpness), `table` (the table plane of real scenes), `regularizers` (finite-difference Eikonal and
smoothness), `optim` (a small Adam), `problem` (tensors built from a SceneData), `model` (the preset's ReconModel),
`mesh` (marching cubes with cleaning).
"""
