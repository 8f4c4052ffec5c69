"""Reconstruction by differentiable transient rendering.

The parts are separate, as in a radiance-field library, so that the presets share everything except the field and
its schedule:

- `config`: dataclass configs and the one registry of presets (`paper`, `fast`);
- `scene_data`: a capture loaded into tensors (counts, poses, sensor, pulse, bounds, table);
- `rays`: rays stratified in solid angle over each zone's field of view, with importance resampling;
- `render`: NeuS-style volume rendering of an SDF field along rays (opacity, round-trip transmittance, radiance);
- `forward`: the sensor model in torch (range binning, pulse, gains, crosstalk, background, pile-up, likelihoods);
- `model_api`: the protocol every preset's model implements (`step`, `extract_mesh`, `render_histograms`);
- `mesh`: marching cubes of an SDF with normals from its gradient;
- `paper/`: the paper's method (MLP SDF with positional encoding).
"""
