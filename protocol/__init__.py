"""What both halves of spadscan share: data formats, the sensor model and its physics, the simulator.

Imports only numpy, trimesh and the standard library (never torch or hardware libraries).
"""
