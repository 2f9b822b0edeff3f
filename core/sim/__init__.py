"""The simulated cell, the plant: it holds the TRUE cell and stands in for hardware.
The simulated robot backend and vacuum, the renderer and camera, the JRC emulator.

It imports every layer below it (geometry .. servo); production, calibration and study
reach it only to build a simulated rig or to run experiments.
"""

from enum import StrEnum


class Arm(StrEnum):
    """What carries the camera in a simulated cell (here, not in plant.py: the command line
    offers the choice without loading the simulator)."""

    UPJ = "upj"  # the cell's arm, moved by its controller (the JRC's logic)
    NONE = "none"  # nothing: a free-flying camera, to study a control law alone
