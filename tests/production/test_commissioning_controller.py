"""Commissioning through the controller, as the Calibrate tab drives it: over the channel,
on the simulated cell (the rig lays the board itself), then Apply and a run on the new model."""

from __future__ import annotations

import shutil
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from vservo.core.cell.config import load_cell
from vservo.core.production.assembly import Outcome, Phase
from vservo.core.production.cell_controller import CellController, CommandRefused, commissioned_path
from vservo.core.production.channel import ControllerServer
from vservo.core.production.commissioning import CommissionSettings
from vservo.core.production.protocol import ApplyCommissioning, Commission, ControllerClient, Jog, new_key
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.production.storage import DEMO_JOB, Store

SHIPPED = Path(__file__).resolve().parents[2] / "static" / "cell.toml"
# The NN step on a grid too small to trust (at most 3 x 3 views, fewer than the 10 it needs): it says retake.
SMALL_GRID = CommissionSettings(grid_half_m=(0.02, 0.02), grid_step_m=0.02, nn_epochs=5)


class States:
    """Every state the controller publishes, and a wait for one that matches."""

    def __init__(self, controller: CellController) -> None:
        self.seen: list = []
        self._changed = threading.Condition()
        controller.state_subscribers.append(self._on_state)

    def _on_state(self, state) -> None:
        with self._changed:
            self.seen.append(state)
            self._changed.notify_all()

    def wait_for(self, check, what: str, timeout_s: float = 120.0):
        with self._changed:
            if not self._changed.wait_for(lambda: any(check(s) for s in self.seen), timeout_s):
                raise AssertionError(f"never {what}; last state {self.seen[-1] if self.seen else None}")
            return next(s for s in self.seen if check(s))


def controller_on(config, data: Path) -> tuple[CellController, Store]:
    store = Store(data)
    return CellController(simulated_rig(config, seed=2), store, seed=2), store


@pytest.fixture
def cell_file(tmp_path) -> Path:
    """A copy of the shipped cell file, as an integrator's own cell file."""
    path = tmp_path / "cells" / "line3.toml"
    path.parent.mkdir()
    shutil.copy(SHIPPED, path)
    return path


@pytest.mark.slow
def test_commission_over_the_channel_apply_and_assemble_on_the_new_model(cell_file, tmp_path):
    controller, store = controller_on(load_cell(cell_file), tmp_path / "data")
    states = States(controller)
    frames: list = []
    controller.frame_subscribers.append(frames.append)
    key = new_key()
    server = ControllerServer(controller, key)
    client = ControllerClient(server.address, key)
    try:
        nominal_fx = controller.rig.config.nominal.camera.intrinsics.fx
        reply = client.call(Commission(steps=("camera", "hand-eye", "laser", "nn")))
        assert reply.ok, reply.error
        out = Path(reply.result)
        assert out == cell_file.with_name("line3-commissioned.toml")  # beside the running file
        assert controller.state.phase == Phase.COMMISSIONING.value
        refused = client.call(Jog(translation_m=(0, 0, 0.01)))
        assert not refused.ok and "commissioning is under way" in refused.error
        assert not client.call(Commission()).ok  # one at a time

        finished = states.wait_for(
            lambda s: s.commissioning and (s.commissioning.summary or s.commissioning.error), "finished commissioning"
        )
        record = finished.commissioning
        assert record.error is None and finished.phase == Phase.IDLE.value
        summary = record.summary
        assert summary.good, summary.steps
        assert {step: report.verdict for step, report in summary.steps.items()} == {
            "camera": "good",
            "hand-eye": "good",
            "laser": "good",
            "nn": "good",
        }
        assert summary.acceptance.max_mm < 0.5
        progress = record.progress
        assert {"find", "tilted", "laser", "grid", "nn", "acceptance"} <= set(progress)
        views = {step: line for step, line in progress.items() if step != "nn"}
        assert all(line.done == line.total > 0 for line in views.values()), progress
        assert progress["nn"].done > 0 and progress["nn"].total == 60  # training may end before its last epoch
        # Progress was published as it went, not only at the end.
        records = [s.commissioning for s in states.seen if s.commissioning]
        assert len({record.progress["tilted"].done for record in records if "tilted" in record.progress}) > 5
        assert len(frames) > 20  # what the camera saw was shown
        assert not out.exists()  # nothing is written before Apply

        applied = client.call(ApplyCommissioning(), timeout_s=60.0)
        assert applied.ok, applied.error
        assert Path(applied.result) == out
        written = load_cell(out)
        assert written.commissioning is not None and written.commissioning.nn_path.is_file()
        config = controller.rig.config
        assert config.source == str(out)
        assert config.nominal.camera.intrinsics.fx == pytest.approx(summary.camera.fx_px, abs=1e-3)
        assert config.nominal.camera.intrinsics.fx != pytest.approx(nominal_fx, abs=1e-3)
        assert controller.rig.locator is not None
        assert controller.rig.extractor.camera is config.nominal.camera
        assert controller.state.cell_file == str(out)
        assert controller.state.commissioning.applied == str(out)
        again = client.call(ApplyCommissioning())
        assert not again.ok and "nothing to apply" in again.error

        # The demo job, taught before, assembles on the commissioned model.
        controller.present_part()
        controller.start(DEMO_JOB)
        controller.wait()
        assert controller.last_outcome.outcome is Outcome.PLACED, controller.last_outcome.reason
    finally:
        client.close()
        server.close()
        controller.close()
        store.close()


def test_a_retake_verdict_refuses_apply(tmp_path):
    controller, store = controller_on(load_cell(), tmp_path)
    states = States(controller)
    try:
        out = controller.commission(["nn"], settings=SMALL_GRID)
        assert out == tmp_path / "cell-commissioned.toml"  # the shipped file: into the data folder
        controller.wait()
        summary = states.wait_for(lambda s: s.commissioning and s.commissioning.summary, "summarised").commissioning.summary
        assert summary.steps["nn"].verdict == "retake" and not summary.good
        with pytest.raises(CommandRefused, match=r"a step says retake; commission it again: nn: retake: \d grid views"):
            controller.apply_commissioning()
        assert not out.exists()
        assert controller.rig.config.source == "static/cell.toml"
    finally:
        controller.close()
        store.close()


def test_estop_stops_commissioning_with_the_robot_held(tmp_path):
    controller, store = controller_on(load_cell(), tmp_path)
    states = States(controller)
    try:
        controller.commission()
        states.wait_for(
            lambda s: s.commissioning and "tilted" in s.commissioning.progress and s.commissioning.progress["tilted"].done >= 3,
            "took three tilted views",
        )
        controller.estop()
        controller.wait(60.0)
        assert not controller.running
        state = controller.state
        assert state.phase == Phase.ESTOPPED.value and state.detail == "commissioning stopped: e-stop pressed"
        assert state.commissioning.error == "e-stop pressed" and state.commissioning.summary is None
        assert controller.rig.robot.status().held
        tilted = state.commissioning.progress["tilted"]
        assert tilted.done < tilted.total  # it stopped part way
        with pytest.raises(CommandRefused, match="e-stop is active"):
            controller.commission()
        controller.reset()
        with pytest.raises(CommandRefused, match="nothing to apply"):
            controller.apply_commissioning()
    finally:
        controller.close()
        store.close()


def test_apply_refuses_to_reload_a_file_whose_devices_differ(cell_file, tmp_path):
    controller, store = controller_on(load_cell(cell_file), tmp_path / "data")
    states = States(controller)
    try:
        out = controller.commission(["nn"])
        controller.wait()
        summary = states.wait_for(lambda s: s.commissioning and s.commissioning.summary, "summarised").commissioning.summary
        assert summary.good, summary.steps
        # Someone rewired the cell file the controller runs on meanwhile.
        text = cell_file.read_text()
        assert 'port = "/dev/ttyS0"' in text
        cell_file.write_text(text.replace('port = "/dev/ttyS0"', 'port = "/dev/ttyUSB1"'))
        with pytest.raises(
            CommandRefused,
            match=rf"{out} is written, but its \[jrc\] differ from the running cell's: "
            rf"restart the controller with --cell {out}",
        ):
            controller.apply_commissioning()
        assert load_cell(out).jrc.port == "/dev/ttyUSB1"
        assert controller.rig.config.source == str(cell_file)  # still the running model
    finally:
        controller.close()
        store.close()


def test_commissioning_is_refused_without_a_board_or_with_a_bad_step(tmp_path):
    controller, store = controller_on(replace(load_cell(), board=None), tmp_path)
    try:
        with pytest.raises(CommandRefused, match=r"no \[board\]"):
            controller.commission()
        with pytest.raises(CommandRefused, match="choose from camera, hand-eye, laser, nn"):
            controller.commission(["lens"])
        with pytest.raises(CommandRefused, match="at least one step"):
            controller.commission([])
        controller.begin_teach()
        with pytest.raises(CommandRefused, match="not possible while teaching"):
            controller.commission()
        assert not controller.rig.robot.status().held and np.all(np.isfinite(controller.rig.robot.read_pose()))
    finally:
        controller.close()
        store.close()


def test_where_a_commissioned_file_goes(tmp_path):
    data = tmp_path / "data"
    assert commissioned_path("static/cell.toml", data) == data / "cell-commissioned.toml"
    assert commissioned_path(str(SHIPPED), data) == data / "cell-commissioned.toml"
    cells = tmp_path / "cells"
    cells.mkdir()
    assert commissioned_path(str(cells / "line3.toml"), data) == cells / "line3-commissioned.toml"
    (cells / "line3-commissioned.toml").write_text("")
    assert commissioned_path(str(cells / "line3.toml"), data) == cells / "line3-commissioned-2.toml"
    # Commissioning a commissioned cell again counts on, never line3-commissioned-commissioned.
    assert commissioned_path(str(cells / "line3-commissioned.toml"), data) == cells / "line3-commissioned-2.toml"
