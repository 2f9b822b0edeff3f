"""The operator app's logic without a browser: roles, the command path's checks, the session
built from the controller's real state stream, the live image's overlays, the status texts."""

from __future__ import annotations

import threading
from dataclasses import replace

import cv2
import numpy as np
import pytest
import viser

from tests.jrc_fixtures import with_the_thesis_policy
from vservo.app import commission_text, live_image
from vservo.app.browser import free_port
from vservo.app.calibration_run import bar_fraction, results_markdown, summary_markdown
from vservo.app.commands import CommandQueue
from vservo.app.roles import RoleRefused, Roles, new_token
from vservo.app.scene3d import CellScene, PartTracker, laser_ray, part_pose_from_corners, placed_part_frame
from vservo.app.session import Session
from vservo.app.status import flange_text, outcome_markdown, run_heading, run_progress, runs_table, status_markdown
from vservo.app.teach_panel import jog_step
from vservo.core.cell.config import load_cell, read_cell_bytes
from vservo.core.geometry.spatial import matrix_from_pose, pose_from_mm_deg
from vservo.core.production.cell_controller import CellController
from vservo.core.production.commissioning import Step
from vservo.core.production.jobs import read_job_file
from vservo.core.production.protocol import (
    CommissioningProgress,
    ControllerState,
    Estop,
    FrameMeta,
    Jog,
    ListJobs,
    Outcome,
    Phase,
    Reply,
    RunEntry,
    SaveJob,
    Start,
)
from vservo.core.production.protocol.codec import from_json
from vservo.core.production.protocol.commands import StageCount
from vservo.core.production.simulated_rig import simulated_rig
from vservo.core.production.storage import DEMO_JOB, Store, shipped_job_path

# -- roles -------------------------------------------------------------------------------------


def test_only_the_token_gives_control_and_one_browser_holds_it():
    roles = Roles("s3cret")
    changes = []
    roles.listeners.append(lambda old, new: changes.append((old, new)))
    with pytest.raises(RoleRefused, match="wrong operator token"):
        roles.take(1, "guess")
    assert roles.operator is None
    roles.take(1, " s3cret ")  # pasted with spaces
    assert roles.is_operator(1) and not roles.is_operator(2)
    roles.take(2, "s3cret")  # the token is the authority: a second screen takes over
    assert roles.operator == 2 and changes == [(None, 1), (1, 2)]
    assert not roles.release(1)  # a monitor cannot release someone else's control
    assert roles.disconnected(2) and roles.operator is None
    with pytest.raises(RoleRefused, match="read-only monitor"):
        roles.require(3, "start")


def test_an_empty_token_is_refused_and_new_tokens_differ():
    with pytest.raises(ValueError, match="empty"):
        Roles("  ")
    assert new_token() != new_token() and len(new_token()) >= 16


def test_commands_from_a_monitor_are_refused_before_they_reach_the_controller():
    sent: list = []
    done = threading.Event()

    def call(command, timeout_s: float = 0.0):
        sent.append(command)
        done.set()
        return Reply(True, result="ok")

    roles = Roles("t")
    queue = CommandQueue(call, roles)
    try:
        with pytest.raises(RoleRefused, match="start: this browser is a read-only monitor"):
            queue.submit(7, Start("demo"))
        assert queue.call_now(ListJobs()).ok  # a query is anyone's
        queue.estop(7)  # so is the e-stop
        assert done.wait(5.0)
        roles.take(7, "t")
        replies: list[Reply] = []
        finished = threading.Event()
        queue.submit(7, SaveJob("job-1"), lambda reply: (replies.append(reply), finished.set()))
        assert finished.wait(5.0)
        assert replies[0].ok
        assert sent == [ListJobs(), Estop(), SaveJob("job-1")]
    finally:
        queue.close()


def test_a_queued_command_is_dropped_when_control_changes_hands_before_it_is_sent():
    release, under_way = threading.Event(), threading.Event()
    sent: list[str] = []

    def slow_call(command, timeout_s: float = 0.0):
        under_way.set()
        release.wait(5.0)
        sent.append(command.command_name)
        return Reply(True)

    roles = Roles("t")
    roles.take(1, "t")
    queue = CommandQueue(slow_call, roles)
    replies: list[Reply] = []
    finished = threading.Event()
    try:
        queue.submit(1, Jog(translation_m=(0, 0, 0.001)))
        assert under_way.wait(5.0)
        queue.submit(1, Start("demo"), lambda reply: (replies.append(reply), finished.set()))  # waiting
        roles.take(2, "t")
        release.set()
        assert finished.wait(5.0)
        assert sent == ["jog"] and not replies[0].ok and "control was released" in replies[0].error
    finally:
        queue.close()


# -- the session, from a real controller's state stream --------------------------------------------


@pytest.fixture(scope="module")
def recorded_run(tmp_path_factory):
    """Every state a real assembly publishes, as the channel hands them to the app; with the
    thesis's step policy, for a long trace of small steps."""
    store = Store(tmp_path_factory.mktemp("data"))
    controller = CellController(simulated_rig(with_the_thesis_policy(load_cell()), seed=2), store, seed=2)
    states: list[ControllerState] = []
    controller.state_subscribers.append(states.append)
    controller.present_part()
    controller.start("demo")
    controller.wait()
    outcome = controller.last_outcome
    controller.close()
    store.close()
    return states, outcome


@pytest.mark.slow
def test_the_session_traces_the_run_from_the_state_stream(recorded_run):
    states, outcome = recorded_run
    session = Session()
    for state in states:
        session.on_state(state)
    view = session.view()
    assert view.state.phase is Phase.DONE and view.runs_ended == 1
    trace = view.trace
    assert trace.run_id == states[-1].run.run_id
    assert len(trace.iterations) == outcome.iterations  # one row per servo cycle, none for phase changes
    assert np.all(np.diff(trace.iterations) == 1)
    assert trace.errors_px[-1] == pytest.approx(outcome.final_error_px, abs=1e-9)
    assert trace.twists.shape == (outcome.iterations, 6)
    path_lengths = np.linalg.norm(np.diff(trace.path_m, axis=0), axis=1)
    assert len(trace.path_m) > 10 and np.all(path_lengths >= 0.0005 - 1e-12)
    assert trace.cycle_rate_hz() > 0


@pytest.mark.slow
def test_the_session_ignores_an_older_state_and_starts_a_new_trace_per_run(recorded_run):
    states, _ = recorded_run
    session = Session()
    for state in states:
        session.on_state(state)
    session.on_state(replace(states[0], time_s=states[0].time_s - 1.0))  # late welcome
    assert session.state.phase is Phase.DONE
    running = next(s for s in states if s.phase is Phase.SERVOING and s.run.iteration > 0)
    next_run = replace(running.run, run_id=running.run.run_id + 1, iteration=1)
    session.on_state(replace(running, run=next_run, time_s=states[-1].time_s + 1))
    assert list(session.view().trace.iterations) == [1]


def test_wait_for_news_wakes_on_a_frame():
    session = Session()
    threading.Timer(0.05, lambda: session.on_frame(FrameMeta(index=1), b"jpeg")).start()
    assert session.wait_for_news(0, 0, 5.0)
    assert session.view().frame.number == 1


# -- the live image's overlays -------------------------------------------------------------------


def _frame_meta() -> FrameMeta:
    return FrameMeta(
        corners_px=np.array([[100.25, 100.5], [200.0, 100.0], [200.0, 200.0], [np.nan, np.nan]]),
        laser_spot_px=np.array([320.0, 240.0]),
        desired_corners_px=np.array([[400, 300], [500, 300], [500, 400], [400, 400]], float),
        desired_laser_px=np.array([450.0, 350.0]),
        trail_px=np.array([[[50, 50], [60, 50], [60, 60], [50, 60]], [[90, 95], [190, 95], [190, 195], [95, 190]]], float),
    )


def test_overlays_are_drawn_where_the_features_are():
    grey = np.full((480, 640), 40, np.uint8)
    jpeg = cv2.imencode(".jpg", grey)[1].tobytes()
    image = live_image.decode(live_image.render(jpeg, _frame_meta()))
    drawn = cv2.imdecode(np.frombuffer(live_image.render(jpeg, _frame_meta()), np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (480, 640)

    def colour_near(x: float, y: float, radius: int) -> np.ndarray:
        """The most saturated pixel on a ring of ``radius`` around (x, y)."""
        angles = np.linspace(0, 2 * np.pi, 64, endpoint=False)
        ring = drawn[np.round(y + radius * np.sin(angles)).astype(int), np.round(x + radius * np.cos(angles)).astype(int)]
        return ring[np.argmax(ring.max(axis=1).astype(int) - ring.min(axis=1))]

    def close(colour: np.ndarray, bgr: tuple) -> bool:
        return np.abs(colour.astype(int) - np.array(bgr)).max() < 60  # JPEG blurs colours

    assert close(colour_near(100.25, 100.5, 7), live_image.SEEN_BGR)  # a seen corner's ring
    assert close(colour_near(450, 350, 10), live_image.SPOT_BGR)  # the laser's target ring
    assert close(colour_near(400, 300, 6), live_image.DESIRED_BGR)  # a desired corner's square
    assert np.abs(drawn[240, 320].astype(int) - live_image.SPOT_BGR).max() < 60  # the spot's cross
    unseen = drawn[250:270, 250:270]  # nothing drawn for the unseen corner (NaN) or elsewhere
    assert np.abs(unseen.astype(int) - 40).max() < 12


def test_overlay_reads_missing_features_as_nan():
    overlay = live_image.Overlay.from_meta(
        FrameMeta(corners_px=np.array([[1, 2], [np.nan, np.nan], [-1, -1], [3, 4]], float), trail_px=np.zeros((0, 4, 2)))
    )
    assert np.isnan(overlay.corners_px[1:3]).all() and overlay.corners_px[3].tolist() == [3, 4]
    assert overlay.laser_spot_px is None and overlay.trail_px is None


def test_a_bad_jpeg_is_named():
    with pytest.raises(ValueError, match="not a readable JPEG"):
        live_image.decode(b"not a jpeg")


# -- texts and numbers the screens show ---------------------------------------------------------------


@pytest.mark.slow
def test_status_progress_and_outcome_texts(recorded_run):
    states, outcome = recorded_run
    servoing = next(s for s in states if s.phase is Phase.SERVOING and s.run.iteration > 5)
    text = status_markdown(servoing, operator_present=True)
    assert "**Servoing**" in text and f"cycle {servoing.run.iteration}" in text and "an operator holds control" in text
    assert "flange X" in text
    assert "CONTROLLER STOPPED" in status_markdown(servoing, False, controller_gone="exit code 1")
    session = Session()
    progress = []
    for state in states:
        session.on_state(state)
        progress.append(run_progress(state, session.view().trace, 3.0))
    assert progress[-1] == 100.0
    run = [p for p, s in zip(progress, states) if s.phase in (Phase.SERVOING, Phase.PICKING, Phase.PLACING)]
    assert np.all(np.diff(run) >= -1e-9), "the run's progress never goes back"
    last = states[-1].last_outcome
    assert last is not None and last.iterations == outcome.iterations
    assert "Run 7: placed" in outcome_markdown(last, 7) and "placement error" in outcome_markdown(last, 7)


def test_history_texts():
    run = RunEntry(
        id=3,
        job="demo",
        backend="sim",
        started_at=0.0,
        outcome=Outcome.ESTOPPED,
        reason="e-stop pressed",
        duration_s=2.5,
        stages=(StageCount("1A", 30), StageCount("3", 10)),
    )
    table = runs_table([run])
    assert "| 3 | demo | E-STOPPED | 2.5 s | - | - |" in table
    assert run_heading(run) == "**Run 3** (demo): E-STOPPED, e-stop pressed"


def test_flange_text_is_the_pendants_pose():
    bMe = matrix_from_pose(pose_from_mm_deg([-400.0, 12.5, 300.0, 90.0, -10.0, 180.0]))
    assert flange_text(bMe) == "flange X -400.00 Y 12.50 Z 300.00 mm, phi 90.00 theta -10.00 psi 180.00 deg"


def test_jog_steps():
    assert jog_step("-Z", "5 mm / 2 deg") == ([0.0, 0.0, -0.005], [0.0, 0.0, 0.0])
    translation, rotation = jog_step("+Ry", "10 mm / 5 deg")
    assert translation == [0.0] * 3 and rotation == pytest.approx([0.0, np.deg2rad(5.0), 0.0])


def test_calibration_progress_and_table():
    assert bar_fraction("collect planar [#####.........] 7/28 3s 400 corners") == pytest.approx(0.25)
    assert bar_fraction("loading the cell") is None
    table = results_markdown(
        {
            "evaluate": {
                "methods": {"nn": {"x_mm": 0.1, "y_mm": 0.2, "xy_mm": 0.25, "max_xy_mm": 0.5}},
                "corners": 10,
                "views": 2,
            },
            "track": {"methods": {"nn": {"xy_mm": 0.04, "true": {"xy_mm": 0.37}}}, "points": 10},
        }
    )
    assert "| nn | 0.100 | 0.200 | 0.250 | 0.500 | 0.040 | 0.370 |" in table
    plain = summary_markdown({"evaluate": {"methods": {"axxb": {"xy_mm": 1.73}, "nn": {"xy_mm": 0.25}}}})
    assert plain.endswith("- the network: 0.25 mm off on average\n- hand-eye from turned views: 1.73 mm off on average")
    assert "axxb" not in plain and "eq." not in plain


def commissioning_record(nn_verdict: str = "good") -> CommissioningProgress:
    """A finished commissioning as the controller publishes it (figures of the shipped cell's), as the app reads it."""
    nn_why = (
        "validation error 0.298 mm mean over 166 corners"
        if nn_verdict == "good"
        else "retake: 6 grid views, validation error 14.948 mm mean"
    )
    summary = {
        "camera": {"fx_px": 811.178, "fy_px": 811.1212, "principal_point_px": [320.2411, 239.9594]},
        "eMc_mm_deg": [0.0104, -0.0157, -0.0799, 0.0004, 0.0151, -0.0013],
        "cMl_mm_deg": [29.9933, -0.0003, 0.0, 0.0, -10.0105, -0.0029],
        "laser": {"baseline_mm": 29.9933, "alpha_deg": 79.9895},
        "steps": {
            "camera": {
                "views": 24,
                "rms_px": 0.0577,
                "worst_view_rms_px": 0.1412,
                "std_fx_px": 0.4856,
                "verdict": "good",
                "why": "good: RMS 0.058 px over 24 views",
            },
            "nn": {
                "views": 25,
                "corners": 1000,
                "validation_mean_mm": 0.2984,
                "validation_max_mm": 0.8561,
                "verdict": nn_verdict,
                "why": nn_why,
            },
        },
        "acceptance": {"corners": 4, "mean_mm": 0.0101, "max_mm": 0.0152},
        "good": nn_verdict == "good",
        "views": {"taken": 90, "used": 62},
        "cell_time_s": 98.3,
    }
    record = {
        "steps": ["camera", "nn"],
        "out": "/cells/line3-commissioned.toml",
        "step": "acceptance",
        "progress": {
            "tilted": {"done": 24, "total": 24, "note": "40 corners"},
            "nn": {"done": 40, "total": 60, "note": "mse 1.3e-07"},
        },
        "summary": summary,
        "error": None,
        "applied": None,
    }
    return from_json(CommissioningProgress, record)


def test_commissioning_texts():
    assert tuple(commission_text.STEP_WORDS) == tuple(Step)  # the tab offers every step, by its name
    assert "Not commissioned in this session" in commission_text.progress_markdown(None, "static/cell.toml")
    record = commissioning_record()
    running = replace(record, summary=None)
    text = commission_text.progress_markdown(running, "/cells/line3.toml")
    assert text.startswith("The controller runs on `/cells/line3.toml`.")
    assert "**Commissioning** camera, nn; the new cell file will be `/cells/line3-commissioned.toml`." in text
    assert "- tilted views (camera, hand-eye): 24 of 24 views (last: 40 corners)" in text
    assert "- training the network: epoch 40 of at most 60, mse 1.3e-07" in text
    assert commission_text.results_markdown(running) == ""

    finished = commission_text.progress_markdown(record, "/cells/line3.toml")
    assert "**Commissioned**: every step is good. **Apply** writes `/cells/line3-commissioned.toml`." in finished
    assert "24 of 24 views\n" in finished and "last:" not in finished  # a good step's last note is no failure
    skipped = replace(running, progress={"tilted": replace(running.progress["tilted"], note="unreachable")})
    assert "(last: out of the arm's reach, skipped)" in commission_text.progress_markdown(skipped, "/cells/line3.toml")
    plain = commission_text.results_markdown(record)
    assert plain.startswith("- camera: good\n- network (nn): good\n") and "RMS" not in plain and "eMc" not in plain
    assert "the figure to sign off**: mean error **0.010 mm**, max **0.015 mm** over 4 board corners" in plain
    table = commission_text.engineering_markdown(record)
    assert "| camera | RMS 0.058 px over 24 views (worst view 0.141 px); fx known to ±0.49 px |" in table
    assert "| network (nn) | validation error 0.298 mm mean, 0.856 mm max (1000 corners from 25 views) |" in table
    assert "- camera: fx 811.18 px, fy 811.12 px, principal point (320.24, 239.96) px\n" in table
    assert "- laser cMl: X 29.993 Y -0.000 Z 0.000 mm, phi 0.000 theta -10.011 psi -0.003 deg (not measured" in table
    assert "- laser baseline d 29.99 mm, angle alpha 79.99 deg (not measured: the cell file's)" in table
    assert commission_text.apply_question(record) == (
        "Write `/cells/line3-commissioned.toml` and reload the controller's model from it?"
    )

    retake = commissioning_record("retake")
    assert "**Commissioned**, but nn says retake: commission again." in commission_text.progress_markdown(retake, "x")
    assert "- network (nn): **retake**: 6 grid views, validation error 14.948 mm mean" in commission_text.results_markdown(retake)

    stopped = replace(running, error="e-stop pressed")
    assert "**Commissioning stopped**: e-stop pressed" in commission_text.progress_markdown(stopped, "x")
    applied = replace(record, applied="/cells/line3-commissioned.toml")
    text = commission_text.progress_markdown(applied, "/cells/line3-commissioned.toml")
    assert text.startswith("**Applied**: the controller's model is now `/cells/line3-commissioned.toml`.")


# -- the 3D view's geometry (the controller's picture, from measurements) ---------------------------------


def test_the_part_is_placed_from_its_corners_and_carried_by_the_cup():
    config = load_cell()
    rig = simulated_rig(config, seed=1)
    rig.robot.connect()
    frame = rig.camera.read()
    features, _ = rig.extractor.extract(frame.image)
    bMe = rig.robot.read_pose()
    mount, camera = config.nominal.mount, config.nominal.camera
    bMo = part_pose_from_corners(features.corners_px, bMe, mount.eMc, camera, 0.020)
    true_bMo = rig.cell.state.scene.cube.bMo
    assert np.abs(bMo[:3, 3] - true_bMo[:3, 3]).max() < 0.002  # the nominal cell is the true one here

    tracker = PartTracker(mount, camera)
    overlay = live_image.Overlay(corners_px=features.corners_px)
    state = ControllerState(bMe=bMe, holding_part=False)
    assert np.allclose(tracker.update(state, overlay, 0.020), bMo)
    tracker.update(ControllerState(bMe=bMe, holding_part=True), None, 0.020)  # grasped here
    lifted = bMe.copy()
    lifted[2, 3] += 0.1
    carried = tracker.update(ControllerState(bMe=lifted, holding_part=True), None, 0.020)
    assert np.allclose(carried[:3, 3], bMo[:3, 3] + [0, 0, 0.1]) and np.allclose(carried[:3, :3], bMo[:3, :3])
    hidden = live_image.Overlay(corners_px=np.full((4, 2), np.nan))
    assert np.allclose(tracker.update(ControllerState(bMe=bMe, holding_part=False), hidden, 0.020), carried)

    start, end = laser_ray(bMe, mount.eMl, float(bMo[2, 3]))
    assert end[2] == pytest.approx(bMo[2, 3]) and np.linalg.norm(end - start) > 0.05


def test_after_an_apply_the_3d_view_draws_the_tools_where_the_commissioned_file_puts_them(tmp_path):
    """The controller's state names the cell file it runs on: the scene follows it (a real
    viser server, no browser), and an unreadable one leaves the tools as they were."""
    shipped = load_cell()
    text = read_cell_bytes()[0].decode()
    for nominal, measured in (
        ("eMc = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]", "eMc = [12.0, -5.0, 30.0, 1.0, 0.0, 3.0]"),
        ("focal_length_mm = 6.0", "focal_length_mm = 6.3"),
    ):
        assert nominal in text
        text = text.replace(nominal, measured)
    commissioned = tmp_path / "cell-commissioned.toml"
    commissioned.write_text(text)
    eMc = load_cell(commissioned).nominal.mount.eMc
    assert not np.allclose(eMc, shipped.nominal.mount.eMc)

    server = viser.ViserServer(host="127.0.0.1", port=free_port(), verbose=False)
    try:
        scene = CellScene(server, shipped)
        bMe = matrix_from_pose(pose_from_mm_deg([-300.0, 50.0, 250.0, 180.0, 0.0, 30.0]))
        state = ControllerState(q=shipped.home_q, bMe=bMe, cell_file=shipped.source)
        scene.update(state, None, np.zeros((0, 3)))
        assert np.allclose(scene.frustum.position, (bMe @ shipped.nominal.mount.eMc)[:3, 3])
        fov_shipped = scene.frustum.fov

        scene.update(replace(state, cell_file=str(commissioned)), None, np.zeros((0, 3)))
        assert np.allclose(scene.frustum.position, (bMe @ eMc)[:3, 3])
        assert scene.frustum.fov < fov_shipped  # a longer lens sees less
        assert scene.tracker.mount.eMc is scene.mount.eMc  # the part is placed through the new camera too

        scene.update(replace(state, cell_file=str(tmp_path / "gone.toml")), None, np.zeros((0, 3)))
        assert np.allclose(scene.frustum.position, (bMe @ eMc)[:3, 3])
    finally:
        server.stop()


def test_the_metal_part_sits_under_the_demo_jobs_place_pose():
    config = load_cell()
    demo = read_job_file(shipped_job_path(DEMO_JOB))
    bMp = placed_part_frame(demo.bMe_place, config.nominal.mount.eMv, demo.part_side_m)
    true_bMp = simulated_rig(config, seed=1).cell.state.scene.metal_part.bMp
    assert np.abs(bMp[:3, 3] - true_bMp[:3, 3]).max() < 0.004  # the cup taught 3 mm into its compensator
    assert bMp[2, 2] == pytest.approx(1.0, abs=1e-6)  # the pocket opens upwards
