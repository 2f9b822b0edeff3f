"""The operator application (`vservo serve`): the browser UI on viser, talking to the controller process.

server.py wires it; one module per concept (session, roles, commands, live image, 3D scene,
the four tabs). The controller process (core/cell_controller.py, core/channel.py) owns the
cell; this package only shows it and sends the operator's commands.
"""
