"""The paper's reconstruction method (preset `paper`): an MLP SDF with positional encoding, rendered NeuS-style.

`model` (the preset's ReconModel) on `config`, `field` (the MLP), `rays` (rays stratified in solid angle per zone,
with importance resampling), `sampler` (stratified and importance samples in the scene sphere), `render` (volume
rendering with round-trip transmittance), `batch` (memory-bounded back-propagation of a batch of rays), `pipeline`
(from a field and views to binned transients), `loss` (the paper's L2, Eikonal, normal TV) and `mesh` (marching
cubes of an SDF callable).
"""
