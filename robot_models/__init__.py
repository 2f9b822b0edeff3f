"""The arm descriptions: the UPJ's DH table, its URDF generator, and the loader that also
serves example-robot-data's arms.
"""

if __name__ != "vservo.robot_models":  # one import name: a second copy would split every class in two
    raise ImportError(f"vservo's robot_models is imported as vservo.robot_models, not as {__name__!r}")
