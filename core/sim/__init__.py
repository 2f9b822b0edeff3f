"""The simulated cell, the plant: it holds the TRUE cell and stands in for hardware.
The simulated robot backend and vacuum, the renderer and camera, the JRC emulator.

It imports every layer below it (geometry .. servo); production, calibration and study
reach it only to build a simulated rig or to run experiments.
"""
