"""The PLC handshake (docs/plc.md): the line's PLC starts runs and reads their results.

``handshake.py`` is the state machine on typed signals, ``service.py`` polls it in the
controller process and carries its starts and resets out through the controller's own
guards; the signals travel on a Modbus TCP server (``modbus.py``) or the JRC's I/O lines
(``jrc_lines.py``). None of them moves the robot: the controller does, as for the page.
"""
