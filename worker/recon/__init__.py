"""Reconstruction by differentiable transient rendering: two presets on a few shared modules.

Shared by both presets (and by the run code, `worker/reconstruct.py`):

- `presets`: the one registry of presets (`paper`, `fast`), each its config and its model factory;
- `config`: the run settings every preset's config shares, and `--set KEY=VALUE` overrides;
- `scene_data`: a capture loaded into tensors (counts, poses, sensor, pulse, bounds, table);
- `forward`: the sensor model in torch (range binning, pulse, gains, crosstalk, background, pile-up, likelihoods);
- `model_api`: the protocol every preset's model implements (`step`, `extract_mesh`, `render_histograms`);
- `trainer`: the one training loop (budget, steps, checkpoints, early stop);
- `errors`, `numerics`.

Each preset keeps its own field, sampler, renderer, losses and meshing: `fast/` (an SDF grid started and bounded by
the space-carving hull, its mechanisms as parts) and `paper/` (the published method: an MLP SDF rendered NeuS-style).
What the histograms show without a model (first returns, carving, the pulse, the table height) lives outside, in
`worker.carving`, `worker.pulse` and `worker.table_height`, which the baselines share.
"""
