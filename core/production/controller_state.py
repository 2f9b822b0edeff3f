"""What the cell controller's parts share: the teach draft, the frames shown, how they publish.

The controller (cell_controller.py) owns three parts, each in its own module: teaching
(teaching_session.py), an assembly run (assembly_run.py) and commissioning
(commissioning_session.py). They change what the controller publishes (the protocol's
ControllerState, core/production/protocol/state.py) only through a ``Publisher``, which
the controller implements under its state rule (its module docstring), and they read the
e-stop through an ``EStopLatch``. What they refuse with is the protocol's CommandRefused.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.camera_source import Frame
from vservo.core.perception.features import DesiredImage
from vservo.core.production.jobs import TaughtModel
from vservo.core.production.placement_check import CheckView
from vservo.core.production.protocol import ControllerState, TeachStep
from vservo.core.production.protocol.commands import NEW_JOB_SETTINGS


@dataclass(frozen=True)
class TeachDraft:
    """A job being taught: what has been captured so far."""

    template: str | None = None
    desired: DesiredImage | None = None
    taught_bMe: Matrix | None = None
    start_bMe: Matrix | None = None
    eMe_pick: Matrix | None = None
    bMe_place: Matrix | None = None
    threshold_px: float = NEW_JOB_SETTINGS.threshold_px
    gain: float = NEW_JOB_SETTINGS.gain
    approach_m: float = NEW_JOB_SETTINGS.approach_m
    check: CheckView | None = None
    placement_tolerance_mm: float = NEW_JOB_SETTINGS.placement_tolerance_mm
    taught_model: TaughtModel | None = None  # what the desired image was seen through
    seen_bMo: Matrix | None = None  # the part as the desired image saw it (planar PnP, nominal camera)

    @property
    def taught(self) -> frozenset[TeachStep]:
        """The steps this draft has taught."""
        captured = {
            TeachStep.DESIRED_IMAGE: self.desired,
            TeachStep.START_POSE: self.start_bMe,
            TeachStep.PICK_POSE: self.eMe_pick,
            TeachStep.PLACE_POSE: self.bMe_place,
            TeachStep.CHECK_VIEW: self.check,
        }
        return frozenset(step for step, value in captured.items() if value is not None)

    @property
    def missing(self) -> tuple[TeachStep, ...]:
        """What the job cannot be saved without."""
        return tuple(step for step in TeachStep if step.required and step not in self.taught)


@dataclass(frozen=True)
class FrameView:
    """A camera frame and what the vision saw in it, for the live image."""

    frame: Frame
    corners_px: Matrix | None = None
    laser_spot_px: Matrix | None = None
    desired: DesiredImage | None = None
    trail_px: Matrix | None = None  # (T, 4, 2): corner positions so far in this run


class Publisher(Protocol):
    """What a part of the controller may do to what it publishes (the controller is the one
    implementation; its state rule says who may call these and under which lock)."""

    def update(self, **changes: Any) -> None:
        """Replace these fields of the state and publish it."""

    def update_with(self, changes: Callable[[ControllerState], dict[str, Any] | None]) -> None:
        """Replace the fields ``changes`` computes from the current state (None: nothing) and publish it."""

    def robot_readout(self, bMe: Matrix | None = None, vacuum: bool = True, q: Matrix | None = None) -> dict[str, Any]:
        """The flange pose, joints (``q`` when the caller has the model's joints of bMe) and
        (``vacuum``) the vacuum sensor as state fields (empty when the link is down)."""

    def publish_frame(self, view: FrameView) -> None:
        """Show a camera frame and what was seen in it."""


class EStopLatch:
    """The e-stop as every thread reads it: pressed until reset, and why it was pressed."""

    def __init__(self) -> None:
        self._pressed = threading.Event()
        self.reason = "e-stop pressed"

    def press(self, why: str) -> None:
        self.reason = why  # before the latch: a thread that sees it pressed reads this reason
        self._pressed.set()

    def release(self) -> None:
        self._pressed.clear()

    def is_set(self) -> bool:
        return self._pressed.is_set()
