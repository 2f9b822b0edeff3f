"""The operator application (`vservo serve`): the browser UI on viser, talking to the controller process.

server.py wires it; one module per concept (session, roles, commands, live image, 3D scene,
the four tabs). The controller process (core/production/cell_controller.py, core/production/channel.py) owns the
cell; this package only shows it and sends the operator's commands.
"""

if __name__ != "vservo.app":  # one import name: a second copy would split every class in two
    raise ImportError(f"vservo's app is imported as vservo.app, not as {__name__!r}")
