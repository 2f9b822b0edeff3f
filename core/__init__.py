"""vservo's headless library, one folder per layer, lowest first:

geometry     poses, the camera model, interaction matrices, the laser, pose estimation
cell         the cell file, the scene's objects, the arm's kinematics
perception   measurements, image features, detectors, camera sources, recording
robot        the backend protocol and its commands, the safety layer, the JRC link
servo        control laws, the look-and-move loop, step policies, teaching
sim          the plant (the TRUE cell), its camera and renderer, the JRC emulator
calibration  the NN hand-eye calibration and the classical methods
production   jobs, storage, assembly, the cell controller and its channel, the rig
study        the thesis's tasks, Monte Carlo, reports, figures, benches

A layer imports only layers above it in this list (tests/project/test_layers.py checks it on
the import graph), so nothing in perception, servo or robot sees the simulator and
production never depends on the study. Under all of them, terminal/ holds what every
layer's command line shares (each layer registers its commands from its own cli.py on
the parser that vservo.app.cli builds) and the progress bar; it imports nothing else of
vservo. errors.py holds VservoError, the root of every error vservo raises on purpose.
"""

if __name__ != "vservo.core":  # a second copy under another name would split every class and enum in two
    raise ImportError(f"vservo's core is imported as vservo.core, not as {__name__!r}")
