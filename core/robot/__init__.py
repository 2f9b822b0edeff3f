"""Robots: the backend protocol every robot implements, its commands, the safety layer,
the vacuum cup's protocol, and the JRC link over RS-232 (BSC data link and host commands).

It imports geometry, cell and perception; never the simulator: the protocol does not
need the plant, and the JRC link talks only to a serial port.
"""
