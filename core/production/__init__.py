"""Production: taught jobs, their SQLite store, one-click assembly, the cell controller
(its state machine and process) and its channel, and the rig it drives.

It imports every layer below it, the simulator for the simulated rig; never study.
"""
