"""The values the cell controller publishes and refuses with, shared by its parts.

The controller (cell_controller.py) owns three parts, each in its own module: teaching
(teaching_session.py), an assembly run (assembly_run.py) and commissioning
(commissioning_session.py). They change what the controller publishes only through a
``Publisher``, which the controller implements under its state rule (its module docstring),
and they read the e-stop through an ``EStopLatch``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import Any, Protocol

import numpy as np

from vservo.core.errors import VservoError
from vservo.core.geometry.spatial import Matrix
from vservo.core.perception.camera_source import Frame
from vservo.core.perception.features import DesiredImage
from vservo.core.production.assembly import Phase
from vservo.core.production.jobs import Job, TaughtModel
from vservo.core.production.placement_check import CheckView
from vservo.core.servo.laws.base import Stage


class CommandRefused(VservoError):
    """A command that cannot be carried out now; the message says why."""


@dataclass(frozen=True)
class TeachDraft:
    """A job being taught: what has been captured so far."""

    template: str | None = None
    desired: DesiredImage | None = None
    taught_bMe: Matrix | None = None
    start_bMe: Matrix | None = None
    eMe_pick: Matrix | None = None
    bMe_place: Matrix | None = None
    threshold_px: float = Job.threshold_px
    gain: float = 1.0
    approach_m: float = 0.04
    check: CheckView | None = None
    placement_tolerance_mm: float = 1.0
    taught_model: TaughtModel | None = None  # what the desired image was seen through
    seen_bMo: Matrix | None = None  # the part as the desired image saw it (planar PnP, nominal camera)

    def missing(self) -> list[str]:
        """What the job cannot be saved without."""
        names = {
            "desired": "the desired image",
            "start_bMe": "the start pose",
            "eMe_pick": "the pick pose",
            "bMe_place": "the place pose",
        }
        return [text for key, text in names.items() if getattr(self, key) is None]

    def optional_missing(self) -> list[str]:
        """What the job can be saved without, at a cost the operator should know."""
        return ["the check view (without it, runs report placement unknown)"] if self.check is None else []


@dataclass(frozen=True)
class ControllerState:
    """What every screen shows; published on every change and every servo cycle."""

    phase: str = Phase.IDLE.value
    detail: str = ""
    job: str | None = None
    run_id: int | None = None
    stage: Stage | None = None
    iteration: int = 0
    error_px: float | None = None
    cVc: list[float] = field(default_factory=lambda: [0.0] * 6)
    bMe: list[list[float]] = field(default_factory=lambda: np.eye(4).tolist())
    q: list[float] = field(default_factory=list)
    holding_part: bool = False
    robot: str = ""
    backend: str = ""
    can_present_part: bool = False  # the cell can put a new part on the table (simulated, or a test fixture)
    teach_missing: list[str] = field(default_factory=list)
    teach_optional: list[str] = field(default_factory=list)
    # While teaching, the poses the Teach tab offers to go to, each once known: "view_bMe"
    # the desired view; from the cell file's [metal_part], "pocket_bMe" the flange pose that
    # sets the picked part down centred in its pocket, "place_bMo" where the taught place sets it.
    teach_poses: dict[str, list[list[float]]] = field(default_factory=dict)
    last_outcome: dict | None = None
    cell_file: str = ""  # the cell file whose model the controller runs on
    # The commissioning of this session: its steps, the file Apply writes, per step of the
    # procedure the views (or epochs) done of total and the last note, then the summary
    # (commission_summary), or the error that stopped it; "applied" once written and reloaded.
    commissioning: dict | None = None
    time_s: float = 0.0

    def as_dict(self) -> dict:
        return asdict(self)


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

    def robot_readout(self, bMe: Matrix | None = None) -> dict[str, Any]:
        """The flange pose, joints and vacuum sensor as state fields (empty when the link is down)."""

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


def commissioning_record(state: ControllerState) -> dict[str, Any]:
    """The state's commissioning record (empty before any commissioning)."""
    return state.commissioning or {}
