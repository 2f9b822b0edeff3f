"""Lost devices and runs (docs/reliability.md): a JRC port that goes away and comes back,
a recording that cannot be written, a run killed or interrupted, an e-stop behind a
silent link. Real ptys, the real emulator and virtual cell, real processes."""

from __future__ import annotations

import os
import shutil
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.jrc_fixtures import TIME_SCALE, short_timer_cell, thesis_policy_cell_file, with_the_thesis_policy
from tests.polling import wait_until
from tests.virtual_cell_process import VirtualCellProcess
from vservo.core.cell.config import load_cell
from vservo.core.perception.recording import Recording
from vservo.core.production.assembly import Outcome, Phase
from vservo.core.production.cell_controller import HOLD_CONFIRM_S, CellController
from vservo.core.production.cell_rig import build_rig
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.production.storage import Store
from vservo.core.robot.bsc import LinkError
from vservo.core.robot.jrc import JrcBackend
from vservo.core.sim.jrc_emulator import JrcEmulator
from vservo.core.sim.plant import SimulatedCell

ROOT = Path(__file__).resolve().parents[2]
STOPPED_ON_RECORD_WITHIN_S = 1.0  # a run ends on record this soon after Ctrl-C or the e-stop (0.03 to 0.1 s measured)


def test_a_lost_jrc_port_raises_link_error_and_connect_opens_it_again_when_it_is_back(tmp_path):
    """The emulator's pty closes under the host: every command raises LinkError naming the
    port (never OSError); once a JRC is back under the same name, connect() opens it anew."""
    config = short_timer_cell()
    link = tmp_path / "jrc"
    with JrcEmulator(SimulatedCell(config), config.jrc, time_scale=TIME_SCALE) as first:
        link.symlink_to(first.device)
        robot = JrcBackend(config.jrc, str(link))
        robot.connect()
        robot.read_pose()
    for _ in range(2):  # the command that finds the port gone, and one after it
        with pytest.raises(LinkError, match=f"serial port {link} is lost"):
            robot.read_pose()
    with JrcEmulator(SimulatedCell(config), config.jrc, time_scale=TIME_SCALE) as second:
        link.unlink()
        link.symlink_to(second.device)
        robot.connect()
        assert robot.read_pose().shape == (4, 4)
        robot.close()


def test_a_hold_that_finds_the_port_lost_says_once_that_the_robot_may_still_be_moving(tmp_path):
    config = short_timer_cell()
    with JrcEmulator(SimulatedCell(config), config.jrc, time_scale=TIME_SCALE) as emulator:
        robot = JrcBackend(config.jrc, emulator.device)
        robot.connect()
    with pytest.raises(LinkError) as lost:
        robot.hold(True)
    message = str(lost.value)
    assert message.startswith(f"HOLD failed: the serial port {emulator.device} is lost"), message
    assert message.count("may still be moving") == 1 and "no hold could be sent" not in message, message


def test_a_leftover_run_folder_leaves_the_run_going_unrecorded_and_says_so(tmp_path):
    store = Store(tmp_path / "data")
    controller = CellController(simulated_rig(load_cell(), seed=3), store, seed=3)
    leftover = store.run_folder(1)
    leftover.mkdir(parents=True)
    (leftover / "cycles.jsonl").write_text("not this run's\n")
    controller.present_part()
    run_id = controller.start("demo")
    controller.wait(120)
    assert run_id == 1 and controller.state.phase == Phase.DONE.value
    outcome = controller.last_outcome
    assert outcome.outcome is Outcome.PLACED
    assert any(note.startswith("not recorded: refusing to record into") for note in outcome.notes), outcome.notes
    record = store.run(run_id)
    assert record.outcome is Outcome.PLACED and record.recording is None  # the leftover is not linked as this run's
    controller.close()
    store.close()


def test_a_recording_whose_folder_goes_away_mid_run_stops_and_the_run_ends_on_record(tmp_path):
    store = Store(tmp_path / "data")
    controller = CellController(simulated_rig(with_the_thesis_policy(load_cell()), seed=3), store, seed=3, cycle_period_s=0.01)
    controller.present_part()
    run_id = controller.start("demo")
    wait_until(lambda: controller.state.run.iteration >= 5, "5 cycles", 60, poll_s=0.01)
    folder = store.run_folder(run_id)
    while folder.exists():  # the disk unmounted, the folder removed by hand (the recorder may
        shutil.rmtree(folder, ignore_errors=True)  # write a frame into it meanwhile: remove again)
    controller.wait(120)
    assert not controller.running and controller.state.phase == Phase.DONE.value, controller.state
    assert any(note.startswith("recording stopped at cycle") for note in controller.last_outcome.notes)
    assert store.run(run_id).outcome is Outcome.PLACED
    controller.close()
    store.close()


def _vservo(*args: str, data: Path) -> subprocess.Popen:
    """`vservo run` of the demo job with the thesis's step policy, as typed at a terminal
    (whatever way the tests were started): a servo long enough to act in."""
    # A shell starts a background job with SIGINT ignored and its children inherit that, so
    # Python would install no KeyboardInterrupt handler. A handler is not inherited: exec
    # gives the child SIGINT's default action, as at a terminal. (Not a preexec_fn: the
    # tests' process has threads, and a fork running Python code can deadlock.)
    ignored = signal.getsignal(signal.SIGINT) == signal.SIG_IGN
    if ignored:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return subprocess.Popen(
            [
                sys.executable,
                "-m",
                "vservo.app.cli",
                "run",
                "--job",
                "demo",
                "--data",
                str(data),
                "--cell",
                thesis_policy_cell_file(data.parent),
                *args,
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=ROOT,
        )
    finally:
        if ignored:
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def _recorded_cycles(data: Path) -> int:
    """The cycles of run 1 recorded so far: whole lines (a line follows its frame's file, and
    the recorder's thread writes it a moment after the loop moved on)."""
    cycles = data / "runs" / "000001" / "cycles.jsonl"
    return cycles.read_bytes().count(b"\n") if cycles.is_file() else 0


def test_a_run_killed_with_sigkill_is_marked_interrupted_at_the_next_start_with_its_recording(tmp_path):
    data = tmp_path / "data"
    run = _vservo(data=data)
    wait_until(lambda: _recorded_cycles(data) >= 10 or run.poll() is not None, "10 recorded cycles", 120, poll_s=0.01)
    run.kill()
    run.communicate()
    assert run.returncode == -signal.SIGKILL

    store = Store(data)
    assert store.run(1).outcome is None  # killed: no outcome on record yet
    CellController(simulated_rig(load_cell(), seed=3), store, seed=3).close()  # the next start
    record = store.run(1)
    assert record.outcome is Outcome.INTERRUPTED and "found unfinished" in record.reason
    assert Path(record.recording) == (data / "runs" / "000001").absolute()
    assert len(Recording.open(record.recording).cycles) >= 10
    store.close()
    with sqlite3.connect(data / "vservo.sqlite") as db:  # stored relative to the data folder
        assert db.execute("SELECT recording FROM runs WHERE id = 1").fetchone()[0] == "runs/000001"


def test_an_old_absolute_recording_path_still_reads(tmp_path):
    store = Store(tmp_path / "data")
    run_id = store.start_run("demo", "sim")
    elsewhere = tmp_path / "elsewhere" / "000001"
    store.finish_run(run_id, Outcome.PLACED, "placed", 1.0, 0.1, 1.0, [], elsewhere)
    assert store.run(run_id).recording == str(elsewhere)
    store.close()


def test_ctrl_c_on_vservo_run_holds_records_and_exits_130(tmp_path):
    data = tmp_path / "data"
    run = _vservo(data=data)
    wait_until(lambda: _recorded_cycles(data) >= 5 or run.poll() is not None, "5 recorded cycles", 120, poll_s=0.01)
    sent = time.time()
    run.send_signal(signal.SIGINT)
    _, stderr = run.communicate(timeout=60)
    assert run.returncode == 130, stderr
    assert "Traceback" not in stderr and "terminate called" not in stderr, stderr
    assert "interrupted: Ctrl-C on vservo run" in stderr, stderr
    store = Store(data)
    record = store.run(1)
    assert record.outcome is Outcome.ESTOPPED and record.reason == "Ctrl-C on vservo run"
    assert record.recording is not None
    assert 0 <= record.finished_at - sent < STOPPED_ON_RECORD_WITHIN_S, record.finished_at - sent
    store.close()


@pytest.mark.parametrize("during", ["moving to the start pose", "servoing"])
def test_the_estop_ends_a_run_on_the_virtual_cell_on_record_within_a_second(tmp_path, during):
    """The e-stop during the run's long move to its start pose, and during its servo, through
    the JRC link to `vservo virtual-cell`: the run's stored end follows the press within 1 s."""
    cell = VirtualCellProcess("--seed", "4", "--cell", thesis_policy_cell_file(tmp_path))
    store = Store(tmp_path / "data")
    controller = CellController(build_rig(load_cell(cell.addresses["cell_file"])), store)
    try:
        controller.present_part()
        controller.start("demo")
        if during == "servoing":
            wait_until(lambda: controller.state.run.iteration >= 3, "3 servo cycles", 120, poll_s=0.01)
        else:
            wait_until(lambda: controller.state.detail == during, during, 60, poll_s=0.005)
        pressed = time.time()
        controller.estop()
        controller.wait(30)
        record = store.run(1)
        assert record.outcome is Outcome.ESTOPPED and record.reason == "e-stop pressed", record
        assert 0 <= record.finished_at - pressed < STOPPED_ON_RECORD_WITHIN_S, record.finished_at - pressed
        assert controller.state.phase == Phase.ESTOPPED.value
    finally:
        controller.close()
        store.close()
        cell.stop()


def test_the_estop_behind_a_silent_link_answers_within_a_second_and_says_the_hold_is_not_confirmed(tmp_path):
    """The virtual cell stopped (SIGSTOP) in the middle of a run, on the factory timers: the
    run's request keeps the line for tens of seconds; the e-stop returns at once and the
    state says the hold is not confirmed. Once the cell answers again the hold gets
    through and the state says so."""
    cell = VirtualCellProcess("--seed", "4", "--cell", thesis_policy_cell_file(tmp_path))
    try:
        store = Store(tmp_path / "data")
        controller = CellController(build_rig(load_cell(cell.addresses["cell_file"])), store)
        controller.present_part()
        controller.start("demo")
        wait_until(lambda: controller.state.run.iteration >= 3, "3 cycles", 60, poll_s=0.01)
        os.kill(cell.process.pid, signal.SIGSTOP)
        time.sleep(0.5)  # the run's next request is under way on the silent line
        pressed = time.monotonic()
        controller.estop()
        assert time.monotonic() - pressed < HOLD_CONFIRM_S + 1.0
        assert controller.state.phase == Phase.ESTOPPED.value
        assert "hold NOT confirmed" in controller.state.detail, controller.state.detail
        os.kill(cell.process.pid, signal.SIGCONT)
        wait_until(
            lambda: "robot held" in controller.state.detail or not controller.running, "the hold answered", 120, poll_s=0.01
        )
        controller.wait(120)
        assert store.run(1).outcome is Outcome.ESTOPPED
        controller.close()
        store.close()
    finally:
        os.kill(cell.process.pid, signal.SIGCONT)
        cell.stop()
