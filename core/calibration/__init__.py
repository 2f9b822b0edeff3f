"""The NN hand-eye calibration (thesis chapters 2, 3) and the classical methods it is
compared with: data collection, the MLP and its Levenberg-Marquardt training, the
baselines, PBVS tracking and the evaluation.

It imports the layers below production; the simulator for collecting data on the
simulated cell.
"""
