"""The UR controller emulator on its real ports: RTDE v2 as Universal Robots' guide defines it
(read here with a raw socket, the guide's framing written out independently), the
dashboard server's text lines, and the URScript programs of the script port moving the plant.

ur-rtde's own clients are driven against the emulator in a separate process
(tests/production/test_ur_cell.py): its RTDE constructor holds Python's lock while it waits
for the controller's answers, so an emulator in the same process could never answer it.
"""

import re
import socket
import struct
import time
from pathlib import Path

import numpy as np
import pytest

from vservo.core.cell.config import VacuumDeviceConfig, load_cell
from vservo.core.geometry.spatial import pose_error
from vservo.core.robot import trapezoid, ur_script
from vservo.core.sim.plant import SimulatedCell
from vservo.core.sim.ur_controller import SafetyMode, ScriptError, UrController, UrLimits, parse_program
from vservo.core.sim.ur_emulator import DASHBOARD_PORT, RTDE_PORT, SECONDARY_PORT, UrEmulator
from vservo.robot_models.loader import controller_base

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def emulator():
    emulator = UrEmulator(SimulatedCell(load_cell(), 1), vacuum=VacuumDeviceConfig("ur_io", 0, 0, "tool"))
    emulator.start()
    try:
        yield emulator
    finally:
        emulator.stop()


def package(kind: str, payload: bytes = b"") -> bytes:
    return struct.pack(">HB", 3 + len(payload), ord(kind)) + payload


def receive(connection: socket.socket) -> tuple[str, bytes]:
    header = b""
    while len(header) < 3:
        header += connection.recv(3 - len(header))
    size, kind = struct.unpack(">HB", header)
    payload = b""
    while len(payload) < size - 3:
        payload += connection.recv(size - 3 - len(payload))
    return chr(kind), payload


def rtde(emulator: UrEmulator) -> socket.socket:
    connection = socket.create_connection((emulator.host, RTDE_PORT), timeout=5)
    connection.sendall(package("V", struct.pack(">H", 2)))
    assert receive(connection) == ("V", b"\x01")
    return connection


def test_rtde_negotiates_version_2_names_the_controller_and_types_a_recipe(emulator):
    connection = rtde(emulator)
    with connection:
        connection.sendall(package("v"))
        kind, payload = receive(connection)
        assert kind == "v" and struct.unpack(">IIII", payload)[:2] == (3, 15)  # a CB3: 125 Hz
        # ur-rtde ends the list with a comma; an unknown name is NOT_FOUND and the recipe refused
        connection.sendall(package("O", struct.pack(">d", 125.0) + b"timestamp,actual_TCP_pose,no_such_thing,"))
        kind, payload = receive(connection)
        assert kind == "O" and payload[1:].decode() == "DOUBLE,VECTOR6D,NOT_FOUND"
        connection.sendall(package("O", struct.pack(">d", 125.0) + b"timestamp,actual_TCP_pose,robot_mode,"))
        kind, payload = receive(connection)
        assert payload[0] == 1 and payload[1:].decode() == "DOUBLE,VECTOR6D,INT32"


def test_data_packages_come_every_control_period_on_the_controllers_clock(emulator):
    connection = rtde(emulator)
    with connection:
        connection.sendall(package("O", struct.pack(">d", 125.0) + b"timestamp,actual_TCP_pose"))
        receive(connection)
        connection.sendall(package("S"))
        assert receive(connection) == ("S", b"\x01")
        stamps = []
        while len(stamps) < 20:
            kind, payload = receive(connection)
            if kind == "U":
                recipe, timestamp, *pose = struct.unpack(">B7d", payload)
                stamps.append(timestamp)
    steps = np.diff(stamps)
    assert np.allclose(steps, 1.0 / 125.0, atol=1e-9)  # one package a period, none skipped
    with emulator.lock:
        bMe = emulator.controller.tcp_pose()
    assert pose_error(ur_script.pose_from_ur(pose), bMe)[0] < 1e-9


def dashboard(emulator: UrEmulator, *commands: str) -> list[str]:
    with socket.create_connection((emulator.host, DASHBOARD_PORT), timeout=5) as connection:
        reader = connection.makefile("r")
        assert reader.readline().startswith("Connected: Universal Robots Dashboard Server")
        answers = []
        for command in commands:
            connection.sendall((command + "\n").encode())
            answers.append(reader.readline().strip())
        return answers


def send_program(emulator: UrEmulator, text: str) -> None:
    with socket.create_connection((emulator.host, SECONDARY_PORT), timeout=5) as connection:
        connection.sendall(text.encode())


def wait_for(condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, "the controller did not get there"
        time.sleep(0.01)


def test_the_dashboard_powers_the_arm_and_a_movel_program_brings_the_tcp_to_its_target(emulator):
    assert dashboard(emulator, "robotmode", "power on", "brake release", "robotmode", "nonsense") == [
        "Robotmode: POWER_OFF",
        "Powering on",
        "Brake releasing",
        "Robotmode: RUNNING",
        "could not understand: 'nonsense'",
    ]
    controller = emulator.controller
    with emulator.lock:
        target = controller.tcp_pose()
    target[:3, 3] += [0.02, -0.01, 0.03]
    send_program(emulator, ur_script.program("p", [ur_script.movel(target, 1.2, 0.25)], 41))
    wait_for(lambda: controller.state.registers.get(ur_script.DONE_REGISTER) == 41)
    with emulator.lock:
        translation, rotation = pose_error(controller.tcp_pose(), target)
    assert translation < 1e-6 and rotation < 1e-6


def test_a_speedl_is_held_for_its_time_then_the_arm_stops_by_itself(emulator):
    dashboard(emulator, "power on", "brake release")
    controller = emulator.controller
    with emulator.lock:
        start = controller.tcp_pose()
        sent_s = controller.time_s
    send_program(emulator, ur_script.program("p", [ur_script.speedl([0.05, 0, 0, 0, 0, 0], 1.2, 0.2)], 1))
    wait_for(lambda: controller.motion is None and controller.time_s > sent_s + 0.3)
    with emulator.lock:
        moved = controller.tcp_pose()[0, 3] - start[0, 3]
        stopped_s = controller.last_moved_s
    # accelerate to 50 mm/s, hold until 0.2 s, decelerate: close to 9 mm, and over by 0.2 s + the ramp
    assert 0.007 < moved < 0.011
    assert stopped_s - sent_s <= 0.2 + 0.05 / 1.2 + 2 * controller.period_s


def test_a_dashboard_stop_halts_the_arm_at_the_next_control_period(emulator):
    dashboard(emulator, "power on", "brake release")
    controller = emulator.controller
    send_program(emulator, ur_script.program("p", [ur_script.speedl([0.1, 0, 0, 0, 0, 0], 1.2, 5.0)], 1))
    wait_for(lambda: np.linalg.norm(controller.twist_u[:3]) > 0.09)
    assert dashboard(emulator, "stop") == ["Stopped"]
    with emulator.lock:
        (stop,) = [entry for entry in controller.log if entry.kind == "stop"]
    time.sleep(0.1)
    with emulator.lock:
        assert controller.last_moved_s - stop.time_s <= controller.period_s
        assert not controller.running


def test_a_move_out_of_reach_is_a_protective_stop_until_the_dashboard_unlocks_it(emulator):
    dashboard(emulator, "power on", "brake release")
    controller = emulator.controller
    with emulator.lock:
        far = controller.tcp_pose()
    far[:3, 3] += [0.0, 0.0, -2.0]  # two metres down, through the table and the arm's reach
    send_program(emulator, ur_script.program("p", [ur_script.movel(far, 1.2, 0.25)], 1))
    wait_for(lambda: controller.state.safety_mode is SafetyMode.PROTECTIVE_STOP)
    assert controller.state.registers.get(ur_script.DONE_REGISTER) != 1
    send_program(emulator, ur_script.program("p", [ur_script.stopl(1.2)], 2))
    time.sleep(0.05)
    assert controller.state.registers.get(ur_script.DONE_REGISTER) != 2  # refused while stopped
    assert dashboard(emulator, "safetystatus", "unlock protective stop", "safetystatus") == [
        "Safetystatus: PROTECTIVE_STOP",
        "Protective stop releasing",
        "Safetystatus: NORMAL",
    ]


def test_the_cup_on_a_tool_output_grips_and_its_switch_reads_on_the_tool_input(emulator):
    dashboard(emulator, "power on", "brake release")
    controller = emulator.controller
    send_program(emulator, ur_script.program("p", [ur_script.set_digital_out(ur_script.DigitalOutputs.TOOL, 0, True)], 5))
    wait_for(lambda: controller.state.registers.get(ur_script.DONE_REGISTER) == 5)
    assert controller.digital_output_bits() == 1 << 16  # tool output 0
    assert controller.digital_input_bits() == (1 << 16 if controller.cell.holding_part else 0)


@pytest.mark.parametrize(
    "text, words",
    [
        ("def p():\n  movel(p[0, 0, 0, 0, 0], a=1, v=1)\nend\n", "a pose has 6 numbers"),
        ('def p():\n  popup("hello")\nend\n', "not a statement this controller runs"),
        ("def p():\n  stopl(1)\n", "a program is 'def name():' ... 'end'"),
    ],
)
def test_a_program_it_cannot_run_is_refused_naming_the_line(text, words):
    with pytest.raises(ScriptError, match=re.escape(words)):
        parse_program(text)


def test_the_controllers_speed_limit_caps_a_streamed_twist():
    controller = UrController(SimulatedCell(load_cell(), 1), limits=UrLimits(max_speed_m_s=0.05))
    controller.power(True)
    controller.run_program(ur_script.program("p", [ur_script.speedl([0.5, 0, 0, 0, 0, 0], 100.0, 0.5)], 1))
    for _ in range(5):
        controller.tick()
    assert controller.state.safety_mode is SafetyMode.NORMAL
    assert np.linalg.norm(controller.twist_u[:3]) == pytest.approx(0.05)


def test_a_ur5_speaks_in_its_controllers_base_frame_half_a_turn_from_the_urdfs_root():
    """At zero joints a real UR5 shows its TCP at (-817.25, -191.45, -5.49) mm in its Base
    (a2 + a3, -(d4 + d6), d1 - d5 of Universal Robots' DH table); example-robot-data's model
    puts it at (817.25, 191.45, -5.49) mm in its root base_link."""
    config = load_cell(ROOT / "static" / "cell-ur5.toml")
    cell = SimulatedCell(config, 1)
    controller = UrController(cell)
    cell.move_joints(np.zeros(6), 0.0)
    uMe = controller.tcp_pose()
    assert np.allclose(uMe[:3, 3], [-0.81725, -0.19145, -0.00549], atol=1e-5)
    assert np.allclose(cell.jrc_arm.fk(cell.state.q)[:3, 3], [0.81725, 0.19145, -0.00549], atol=1e-5)
    # from the cell's home (the zero joints are singular), a movel to a pose in Base: the arm
    # model's flange ends at that pose carried into base_link
    cell.move_joints(config.home_q, 0.0)
    target = controller.tcp_pose()
    target[:3, 3] += [0.03, -0.02, 0.04]
    controller.power(True)
    controller.run_program(ur_script.program("p", [ur_script.movel(target, 1.2, 0.25)], 1))
    while controller.running:
        controller.tick()
    assert controller.state.safety_mode is SafetyMode.NORMAL
    translation, rotation = pose_error(cell.jrc_arm.fk(cell.state.q), controller_base("ur5") @ target)
    assert translation < 1e-6 and rotation < 1e-6


def run_to_the_end(controller: UrController) -> list[tuple[float, np.ndarray]]:
    """Tick until the program has ended and the arm stands; each period's clock and joints."""
    ticks = []
    while controller.running or controller.motion is not None:
        controller.tick()
        ticks.append((controller.time_s, controller.q.copy()))
    return ticks


@pytest.mark.parametrize("duration_s", [1.5, 0.0])
def test_a_movej_runs_every_joint_on_the_straight_line_to_its_target_in_its_time(duration_s):
    """t given: the move lasts t; t = 0: the leading joint's trapezoid of a and v. On the
    way every joint is on the straight line from the start's to the target's, the TCP
    reported (in the controller's Base) is where the model puts the flange at those joints."""
    cell = SimulatedCell(load_cell(), 1)
    controller = UrController(cell)
    controller.power(True)
    q_from = cell.state.q.copy()
    q_to = np.array([float(f"{q:.7g}") for q in q_from + np.radians([20.0, -10.0, 15.0, 5.0, -30.0, 60.0])])  # as sent
    acceleration, speed = 2.0, 0.8
    controller.run_program(ur_script.program("p", [ur_script.movej(q_to, acceleration, speed, duration_s)], 7))
    started_s = controller.time_s
    ticks = run_to_the_end(controller)
    assert controller.state.safety_mode is SafetyMode.NORMAL and controller.state.registers[ur_script.DONE_REGISTER] == 7
    np.testing.assert_allclose(controller.q, q_to, atol=1e-9)
    along = [np.dot(q - q_from, q_to - q_from) / np.dot(q_to - q_from, q_to - q_from) for _, q in ticks]
    off_the_line = max(np.linalg.norm(q - q_from - s * (q_to - q_from)) for s, (_, q) in zip(along, ticks))
    assert off_the_line < 1e-9 and np.all(np.diff(along) >= 0.0)
    moved_s = controller.last_moved_s - started_s
    expected_s = duration_s or trapezoid.duration(float(np.max(np.abs(q_to - q_from))), speed, acceleration)
    assert expected_s <= moved_s <= expected_s + controller.period_s
    translation, rotation = pose_error(controller_base(cell.jrc_arm.name) @ controller.tcp_pose(), cell.jrc_arm.fk(q_to))
    assert translation < 1e-9 and rotation < 1e-9


def test_a_movej_beyond_the_joint_limits_is_a_protective_stop_before_the_arm_moves():
    cell = SimulatedCell(load_cell(), 1)
    controller = UrController(cell)
    controller.power(True)
    q_from = cell.state.q.copy()
    q_to = q_from.copy()
    q_to[2] = cell.jrc_arm.upper[2] + np.radians(1.0)
    controller.run_program(ur_script.program("p", [ur_script.movej(q_to, 1.4, 1.05, 0.0)], 3))
    run_to_the_end(controller)
    assert controller.state.safety_mode is SafetyMode.PROTECTIVE_STOP
    assert controller.state.registers.get(ur_script.DONE_REGISTER) != 3
    assert np.array_equal(cell.state.q, q_from)
