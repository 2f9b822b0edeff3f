"""Control laws: classic IBVS, PBVS, 2.5D and the switching IBVS with laser.

Each maps one frame's features to a camera twist, with the error e = s - s* and the
twist v = -lambda L+ e; none holds hidden state or reads the simulator.
"""
