"""The cell model: the cell file (config), the scene's objects and the arm's kinematics.

It imports geometry and vservo.robot_models (the arm descriptions).
"""
