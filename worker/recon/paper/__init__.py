"""The paper's reconstruction method (preset `paper`): an MLP SDF with positional encoding, rendered NeuS-style."""
