"""Perception: what a cell's sensors report and what a control law sees of it.

Measurements, image features, the detectors (vision/), camera sources and run recording.
It imports geometry and cell; never the simulator: a detector sees frames, not the plant.
"""
