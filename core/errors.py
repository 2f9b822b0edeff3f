"""The root of every error vservo raises on purpose.

An error that derives from ``VservoError`` is one the product expected: bad input, a
refused command, a device lost. Its message is meant for the person at the cell, so the
controller's channel answers it as a refusal carrying that message. Anything else that
escapes a command is a bug: the channel answers "internal error" and logs the traceback.

Classes that callers also catch by a builtin base (``ValueError`` for bad values,
``RuntimeError`` for a lost device) keep that base beside this one.
"""


class VservoError(Exception):
    """An error vservo raises on purpose; its message names what is wrong."""
