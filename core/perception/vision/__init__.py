"""Image measurements from one monochrome camera frame (thesis sections 4.3 and 4.4).

Three detectors, each a pure function of a uint8 single-channel image (plus a few
explicit inputs) returning a small frozen record with a ``confidence`` in [0, 1] and a
``reason`` that is "" on success and names the failure otherwise. None of them raises,
whatever the image:

- ``vservo.core.perception.vision.spot.detect_laser_spot``: the laser spot by a fixed-level threshold, its
  centre to a small fraction of a pixel;
- ``vservo.core.perception.vision.corners.detect_corners``: the four corners of the cube's bright top face,
  in the taught order fixed by the orientation mark;
- ``vservo.core.perception.vision.region.detect_object_region``: the object's pixels by a fixed-level
  threshold, their area and centroid by moments (stage 1.B).

Pixel convention (OpenCV): the pixel at row r, column c has its centre at (u, v) = (c, r).

``vservo.core.perception.vision.edges`` holds what the detectors share: input checks, bright regions'
outlines and straight-edge location by the partial-area effect;
``vservo.core.perception.vision.least_squares`` the bounded model fits; ``vservo.core.perception.vision.bands`` the
three-level edge of a side face seen almost edge-on along a side of the top face;
``vservo.core.perception.vision.pipeline`` turns a frame into a control law's features.
"""
