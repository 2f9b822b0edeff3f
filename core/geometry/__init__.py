"""Geometry: rigid-body poses, the camera model, interaction matrices, the laser pointer and pose estimation.

The lowest layer: pure mathematics on numpy arrays. It imports nothing else of vservo.
"""
