"""A simulated Universal Robots controller on loopback that the real ur_rtde client accepts (tests, demo).

It speaks RTDE on port 30004, the dashboard protocol on 29999 and takes the control script on 30003, models motion
time and fake kinematics, records every command it takes, and injects faults (protective and emergency stops,
dropped links). Standard library and numpy only.
"""

from spadscan.daemon.ursim.controller import MoveRecord, URControllerModel
from spadscan.daemon.ursim.sim_controller import LINK_MODES, SimURController

__all__ = ["LINK_MODES", "MoveRecord", "SimURController", "URControllerModel"]
