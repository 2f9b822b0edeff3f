"""NN-based hand-eye calibration (thesis chapters 2, 3) and the classical methods it is
compared with: data collection on the simulated cell, the MLP and its Levenberg-Marquardt
training, the baselines, PBVS tracking and the evaluation."""
