"""Every exception class vservo defines derives from VservoError (core/errors.py).

The channel answers a VservoError as a refusal carrying its message and anything else as an
internal error with its traceback in the log, so a class of ours left outside the root would
reach the operator as a bug. The test imports every module of vservo.core and vservo.app and
checks every exception class defined there.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil

import vservo.app
import vservo.core
from vservo.core.errors import VservoError

# Classes that must not derive from VservoError, each with the reason.
EXEMPT = {
    # The emulator's control flow inside one reply: raised and caught within
    # JrcEmulator._answer, where it becomes the status reply the real controller would send; it never
    # leaves the emulator.
    "vservo.core.sim.jrc_emulator._Refused",
}


def defined_exceptions() -> dict[str, type[BaseException]]:
    """Every exception class defined at module level in vservo.core and vservo.app, by qualified name."""
    found = {}
    for package in (vservo.core, vservo.app):
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            module = importlib.import_module(info.name)
            for name, value in vars(module).items():
                if inspect.isclass(value) and issubclass(value, BaseException) and value.__module__ == module.__name__:
                    found[f"{module.__name__}.{name}"] = value
    return found


def test_every_exception_class_of_vservo_derives_from_vservo_error():
    found = defined_exceptions()
    # The walk reaches the layers (a walk that found nothing would pass vacuously).
    assert {"vservo.core.cell.config.ConfigError", "vservo.core.robot.backend.RobotError"} <= found.keys()
    outside = sorted(name for name, cls in found.items() if not issubclass(cls, VservoError) and name not in EXEMPT)
    assert not outside, f"exception classes outside VservoError: {outside}"


def test_the_exemptions_still_exist_and_are_still_outside():
    """An exemption whose class was renamed, removed or brought under the root is stale."""
    found = defined_exceptions()
    for name in EXEMPT:
        assert name in found, f"{name} is exempt but no longer defined"
        assert not issubclass(found[name], VservoError), f"{name} derives from VservoError: drop its exemption"


def test_the_builtin_bases_callers_catch_are_kept():
    """Callers catch these by their builtin base (a bad value, a lost device): the root sits beside it."""
    from vservo.core.calibration.storage import CalibrationFileError
    from vservo.core.cell.config import ConfigError
    from vservo.core.perception.camera_source import SourceLost
    from vservo.core.servo.laws.base import SingularJacobian

    assert issubclass(ConfigError, ValueError) and issubclass(CalibrationFileError, ValueError)
    assert issubclass(SingularJacobian, ValueError)
    assert issubclass(SourceLost, RuntimeError)
