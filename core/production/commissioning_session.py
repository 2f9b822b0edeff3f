"""Commissioning from the controller: start it, follow its progress, apply its result.

Commissioning (core/production/commissioning.py) measures the cell's model on its board
in the background; ``CommissioningSession.apply`` writes the commissioned cell file and
the controller runs on it from then on: the jobs are retargeted to the new model as
every run starts. The calibration behind it (torch, the board finder) is imported only
when a cell is commissioned.
"""

from __future__ import annotations

import itertools
import logging
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

from vservo.core.cell.config import DEFAULT_CELL, CellConfig, ConfigError, load_cell, read_cell_data
from vservo.core.perception.camera_source import BaseSource, Frame, FrameSource, Size
from vservo.core.production.assembly import hold_after_fault
from vservo.core.production.controller_state import EStopLatch, FrameView, Publisher
from vservo.core.production.locate import PartLocator
from vservo.core.production.protocol import CommandRefused, CommissioningProgress, CommissionSummary, ControllerState, Phase
from vservo.core.production.protocol.catalogue import Refusal
from vservo.core.production.protocol.codec import from_json
from vservo.core.production.protocol.state import ProcedureProgress
from vservo.core.production.rig import Rig, extractor_for

if TYPE_CHECKING:
    from vservo.core.production.commissioning import Commissioning, CommissionResult, CommissionSettings, Progress, Step

log = logging.getLogger("vservo.controller")

# What a commissioned file must share with the running cell for the controller to run on it
# without a restart: the devices it opened (the model is what commissioning changes).
DEVICES: dict[str, Callable[[CellConfig], object]] = {
    "[camera.source]": lambda c: c.camera_source,
    "[jrc]": lambda c: c.jrc,
    "[vacuum] device": lambda c: c.vacuum_device,
    "[robot] backend": lambda c: c.robot_backend,
    "[fixture] url": lambda c: c.fixture_url,
    "arm": lambda c: c.arm,
}


def _record(state: ControllerState) -> CommissioningProgress:
    """The state's commissioning (``begin`` publishes it before the commissioning's thread starts)."""
    if state.commissioning is None:
        raise CommandRefused("nothing was commissioned in this session", Refusal.NOT_COMMISSIONED)
    return state.commissioning


@dataclass(frozen=True)
class Commissioned:
    """A finished commissioning, waiting for Apply: what it measured and where it goes."""

    result: CommissionResult
    out_path: Path
    folder: Path
    steps: list[Step]


@dataclass(frozen=True)
class CommissionPlan:
    """A commissioning checked and ready to start: the procedure, its steps, the cell file
    Apply will write and the folder of its views."""

    commissioning: Commissioning
    steps: list[Step]
    out_path: Path
    folder: Path


def is_shipped_cell(source: str) -> bool:
    """Whether ``source`` names the cell file shipped in static/ (part of the installed package)."""
    shipped = Path(str(resources.files("vservo.static").joinpath(DEFAULT_CELL)))
    return source == f"static/{DEFAULT_CELL}" or Path(source).resolve() == shipped.resolve()


def commissioned_path(source: str, data_folder: Path) -> Path:
    """Where a commissioning of the cell file ``source`` is written unless told: beside it as
    ``<stem>-commissioned.toml`` (``-2``, ``-3``... when taken; a commissioned file's own
    commissioning counts on from its stem), or in the data folder when ``source`` is the
    shipped file, which belongs to the installed package."""
    folder = Path(data_folder) if is_shipped_cell(source) else Path(source).parent
    stem = re.sub(r"-commissioned(-\d+)?$", "", Path(source).stem)
    names = (f"{stem}-commissioned{'' if k == 1 else f'-{k}'}.toml" for k in itertools.count(1))
    return next(folder / name for name in names if not (folder / name).exists())


class _ShownCamera(BaseSource):
    """The rig's camera lent to commissioning: every frame it takes is shown in the live view."""

    def __init__(self, camera: FrameSource, show: Callable[[FrameView], None]) -> None:
        self._camera, self._show = camera, show

    @property
    def image_size(self) -> Size | None:
        return self._camera.image_size

    def read(self) -> Frame:
        return self._shown(self._camera.read())

    def read_after(self, t_s: float) -> Frame:
        return self._shown(self._camera.read_after(t_s))

    def _shown(self, frame: Frame) -> Frame:
        self._show(FrameView(frame))
        return frame

    def close(self) -> None:
        pass  # the controller owns the camera; commissioning only borrows it


class CommissioningSession:
    """This controller's commissioning: the plan under way, then the result waiting for Apply."""

    def __init__(self, rig: Rig, data_folder: Path, seed: int, publisher: Publisher, estop: EStopLatch) -> None:
        self.rig, self.data_folder, self.seed, self.publisher, self.estop = rig, data_folder, seed, publisher, estop
        # Written by the commissioning thread before it publishes its end; read by Apply,
        # which the controller's guards let through only once that thread has ended.
        self._commissioned: Commissioned | None = None

    def plan(
        self, steps: Sequence[Step | str] | None, out_path: str | Path | None, settings: CommissionSettings | None
    ) -> CommissionPlan:
        """Check the request and make the procedure; CommandRefused says what is wrong."""
        from vservo.core.production.commissioning import ALL_STEPS, Commissioning, CommissionSettings, Step

        steps = ALL_STEPS if steps is None else steps
        try:
            chosen = [Step(step) for step in steps]
        except ValueError:
            raise CommandRefused(
                f"commissioning steps {list(steps)!r}: choose from {', '.join(Step)}", Refusal.OUT_OF_RANGE
            ) from None
        if not chosen:
            raise CommandRefused("choose at least one step to commission", Refusal.OUT_OF_RANGE)
        out = Path(out_path) if out_path else commissioned_path(self.rig.config.source, self.data_folder)
        if out.exists():
            raise CommandRefused(
                f"{out} exists: commissioning writes a new cell file, never over another", Refusal.COMMISSION_SETUP
            )
        folder = out.with_name(out.stem + "-commissioning")
        rig = replace(self.rig, camera=_ShownCamera(self.rig.camera, self.publisher.publish_frame))
        try:
            commissioning = Commissioning(
                rig, folder, settings or CommissionSettings(seed=self.seed), self._on_progress, self.estop.is_set
            )
        except ConfigError as exc:
            raise CommandRefused(str(exc), Refusal.COMMISSION_SETUP) from exc
        return CommissionPlan(commissioning, chosen, out, folder)

    def begin(self, plan: CommissionPlan) -> None:
        """Publish the commissioning as started (motion is enabled; its thread starts next)."""
        self._commissioned = None
        self.publisher.update(
            phase=Phase.COMMISSIONING,
            detail=f"commissioning {', '.join(plan.steps)}",
            commissioning=CommissioningProgress(tuple(plan.steps), str(plan.out_path)),
        )

    def _on_progress(self, progress: Progress) -> None:
        line = ProcedureProgress(progress.done, progress.total, progress.note)
        readout = self.publisher.robot_readout()

        def changes(state: ControllerState) -> dict[str, Any]:
            record = _record(state)
            return {
                "detail": f"commissioning: {progress.step} {progress.done}/{progress.total}",
                "commissioning": replace(record, step=progress.step, progress={**record.progress, progress.step: line}),
                **readout,
            }

        self.publisher.update_with(changes)

    def run(self, plan: CommissionPlan) -> None:
        """The commissioning thread: on success the result waits for Apply; any failure
        leaves the robot held, and the state says why."""
        from vservo.core.production.commissioning import CommissioningError, commission_summary

        try:
            result = plan.commissioning.run(plan.steps)
        except Exception as exc:  # a bug as much as a stop must leave the robot held
            if self.estop.is_set():
                error, phase = self.estop.reason, Phase.ESTOPPED
            else:
                if not isinstance(exc, CommissioningError):
                    log.exception("commissioning crashed")
                error, phase = f"{exc}{hold_after_fault(self.rig.robot)}", Phase.FAULT
            self._publish_end(phase, f"commissioning stopped: {error}", error=error)
            return
        self._commissioned = Commissioned(result, plan.out_path, plan.folder, plan.steps)
        retakes = [str(step) for step, step_result in result.steps.items() if not step_result.verdict.good]
        detail = (
            f"commissioned: every step good; Apply writes {plan.out_path}"
            if not retakes
            else f"commissioned: {', '.join(retakes)} say{'s' if len(retakes) == 1 else ''} retake"
        )
        summary = from_json(CommissionSummary, commission_summary(result), "commission_summary")
        self._publish_end(Phase.IDLE, detail, summary=summary)

    def _publish_end(self, phase: Phase, detail: str, **record: Any) -> None:
        readout = self.publisher.robot_readout()
        self.publisher.update_with(
            lambda state: {"phase": phase, "detail": detail, "commissioning": replace(_record(state), **record), **readout}
        )

    def apply(self) -> Path:
        """Write the commissioned cell file and run on its model from now on: the cell's
        model, the feature extractor and the part locator are rebuilt from it. Refused when
        a step says retake or nothing was commissioned; a file whose devices differ from
        the running ones is written, but the controller must be restarted on it."""
        from vservo.core.production.commissioned_file import commissioned_tables, write_commissioned_cell

        done = self._commissioned
        if done is None:
            raise CommandRefused(
                "nothing to apply: commission the cell first (a commissioning is applied once)", Refusal.NOT_COMMISSIONED
            )
        retakes = [f"{step}: {r.verdict.reason}" for step, r in done.result.steps.items() if not r.verdict.good]
        if retakes:
            raise CommandRefused("a step says retake; commission it again: " + "; ".join(retakes), Refusal.NOT_COMMISSIONED)
        running = self.rig.config
        try:
            tables, _ = read_cell_data(None if is_shipped_cell(running.source) else running.source)
            write_commissioned_cell(
                running.source,
                commissioned_tables(tables, done.result, done.out_path, done.folder, done.steps),
                done.out_path,
            )
            self._commissioned = None
            config = load_cell(done.out_path)
            changed = [name for name, device in DEVICES.items() if device(config) != device(running)]
            if changed:
                raise CommandRefused(
                    f"{done.out_path} is written, but its {', '.join(changed)} differ from the "
                    f"running cell's: restart the controller with --cell {done.out_path}",
                    Refusal.COMMISSION_SETUP,
                )
            locator = PartLocator.from_config(config)
        except (ConfigError, OSError) as exc:
            raise CommandRefused(f"apply: {exc}", Refusal.COMMISSION_SETUP) from exc
        self.rig.config, self.rig.extractor, self.rig.locator = config, extractor_for(config), locator
        self.publisher.update_with(
            lambda state: {
                "cell_file": config.source,
                "detail": f"the controller's model is now {config.source}",
                "commissioning": replace(_record(state), applied=config.source),
            }
        )
        return done.out_path
