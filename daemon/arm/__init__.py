"""Arm backends: `ur` (a Universal Robots arm through ur_rtde, in `ur.py`) and `sim` (a simulated arm, in `sim.py`).

Import the backend module you need; this package imports neither, so that a sim rig never loads ur_rtde.
`pose_convert` holds the 4x4 <-> UR pose vector conversions both use.
"""
