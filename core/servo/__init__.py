"""Visual servoing: the control laws (laws/), the look-and-move loop and its failure
monitor, step policies, the four methods and teaching the desired image.

It imports geometry, cell, perception and robot; never the simulator: a control law
sees measurements, the loop drives any robot backend.
"""
