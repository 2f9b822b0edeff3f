"""The cell configuration file (TOML): the nominal cell, its layout, and the simulated truth.

One file describes a cell. Its nominal sections (robot, camera, hand_eye, laser,
vacuum, motion) are what control laws and calibrations may use; ``[camera.source]``
and the ``[vacuum]`` device keys say which devices the controller drives (the
simulator's, or a real camera and the vacuum on the JRC's I/O); ``[jrc]`` holds the
serial line to a JRC, ``[safety]`` the limits on every move, ``[recordings]`` how many
runs' recordings the data folder keeps and ``[line.plc]`` the PLC handshake; ``[simulation]``
describes the plant the simulator plays: its seed and noise, ``[simulation.scene]``
(where the table, cube, metal part and the checkerboard, when laid, really are) and ``[simulation.truth.*]`` tables
that override nominal values with what the cell really is (the robustness test of
Table 5-3 is such a file).

Poses are written as [X, Y, Z, phi, theta, psi] in mm and degrees with
R = Rz(phi) Ry(theta) Rx(psi) (eq. 2-13), the form of the thesis tables; they are
converted to SI once, here. Every error names the file, the key and the bad value.
"""

from __future__ import annotations

import copy
import math
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from enum import StrEnum
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.cell.kinematics import ToolMount
from vservo.core.cell.line import LineConfig, parse_line
from vservo.core.cell.scene import Cube, LaidBoard, MetalPart, Scene
from vservo.core.errors import VservoError
from vservo.core.geometry.camera import CameraModel, Distortion, Intrinsics
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import Matrix, matrix_from_pose, pose_from_mm_deg

DEFAULT_CELL = "cell.toml"


# Bounds of sanity, not of any one cell: beyond them a value is a typo that would break a
# thread or an allocation far from the file (a wait longer than the OS timer, a 1e6 x 1e6 image).
MAX_IMAGE_SIDE_PX = 20_000
MAX_WATCHDOG_S = 600.0


class ConfigError(VservoError, ValueError):
    """A cell configuration that cannot be used; the message names the key and value."""


ROBOT_BACKENDS = ("sim", "jrc")  # the kinematic simulator, the JRC link
CAMERA_SOURCES = ("simulated", "capture", "folder")  # the simulator's renderer, OpenCV VideoCapture, still images
VACUUM_DEVICES = ("simulated", "jrc_io", "none")  # the simulator's cup, the JRC's I/O, no cup


@dataclass(frozen=True)
class CellModel:
    """The parameters calibration estimates and the truth may contradict."""

    camera: CameraModel
    eMc: Matrix
    laser: LaserPointer
    eMv: Matrix

    @property
    def mount(self) -> ToolMount:
        return ToolMount(eMc=self.eMc, eMl=self.eMc @ self.laser.cMl, eMv=self.eMv)


@dataclass(frozen=True)
class BoardConfig:
    """[board]: the calibration checkerboard laid on the table for commissioning.

    ``inner_corners`` is (columns, rows) of inner corners, ``square_m`` the side of a
    square. The board frame has its origin at the inner corner (0, 0) on the board's top
    surface, x along the columns, y along the rows, z up; the square spanning
    [0, s] x [0, s] is black. ``bMboard`` is where the cell file says the board lies: a
    rough place (to a few centimetres and degrees), which commissioning measures.
    """

    square_m: float
    inner_corners: tuple[int, int]
    bMboard: Matrix

    def corners_board(self) -> Matrix:
        """The inner corners (N, 3) in the board frame, row by row (x fastest)."""
        cols, rows = self.inner_corners
        i, j = np.meshgrid(np.arange(cols), np.arange(rows))
        return np.column_stack((i.ravel() * self.square_m, j.ravel() * self.square_m, np.zeros(cols * rows)))


@dataclass(frozen=True)
class CommissioningRecord:
    """[commissioning]: what ``vservo commission`` wrote into a cell file.

    ``nn_path``: the chapter 2 network trained on the cell (read from the cell file's
    folder when relative), which locating a part uses; ``provenance``: the date, the data
    folder and the residuals of each step, kept as written (a record, not a setting).
    """

    nn_path: Path | None
    provenance: dict[str, Any]


@dataclass(frozen=True)
class CameraSourceConfig:
    """[camera.source]: where the controller's frames come from.

    kind "simulated": the simulated cell's renderer. "capture": OpenCV's VideoCapture on
    ``device`` (a device index, a video file, a stream URL or a GStreamer pipeline),
    reopened up to ``reconnect_attempts`` times ``reconnect_delay_s`` apart when a live
    source stops delivering; ``loop`` replays a video file; ``exposure_latency_s`` bounds
    how late a frame arrives after its exposure, so that a servo cycle takes the first
    frame that arrived that long after the motion ended, and ``buffer_frames`` is how many
    more it discards for a pipeline that holds frames inside (docs/vision.md, "No stale
    frames"). "folder": the images of
    ``path`` matching ``pattern``, in name order (a dry run). Every frame must have
    [camera] image_size_px, the size the intrinsics were calibrated at.
    """

    kind: str
    device: int | str | None = None
    reconnect_attempts: int = 3
    reconnect_delay_s: float = 0.5
    loop: bool = False
    exposure_latency_s: float = 0.0
    buffer_frames: int = 0
    path: Path | None = None
    pattern: str = "*.png"

    @property
    def real(self) -> bool:
        """Frames from a device outside the simulator."""
        return self.kind != "simulated"


@dataclass(frozen=True)
class VacuumDeviceConfig:
    """The [vacuum] device: the simulator's cup, the JRC's I/O, or no cup.

    For "jrc_io" (docs/robot-link.md, I/O): ``suction_output`` is the network input the
    host writes, which a ladder line on the controller copies to the valve's output;
    ``grip_input`` the input the cup's pressure switch is wired to. Both are byte.bit
    addresses: the last decimal digit is the bit (0..7), the rest the byte.
    """

    device: str
    suction_output: int | None = None
    grip_input: int | None = None

    def jrc_io(self) -> tuple[int, int]:
        """(suction_output, grip_input) of the "jrc_io" device; ConfigError for a device not wired to the JRC."""
        if self.device != "jrc_io" or self.suction_output is None or self.grip_input is None:
            raise ConfigError(f"the vacuum device {self.device!r} is not wired to the JRC's I/O")
        return self.suction_output, self.grip_input


class StepPolicyKind(StrEnum):
    """Which position steps a JRC-style robot is servoed with (core/servo/step_policy.py)."""

    THESIS = "thesis"  # each step divided by divide_factor, one per sampling period (section 5.3)
    FAST = "fast"  # the law's whole correction within [motion.fast]'s limits, no sampling wait


@dataclass(frozen=True)
class FastStepConfig:
    """[motion.fast]: the largest step of the fast policy and the speed it is moved at;
    within the [safety] limits, which refuse a larger move."""

    max_step_m: float
    max_step_rad: float
    speed_m_s: float


@dataclass(frozen=True)
class MotionConfig:
    """How moves reach the robot (section 5.3: the JRC takes one target at a time)."""

    mode: str  # "position_steps" (JRC style) or "velocity"
    divide_factor: float
    sampling_period_s: float
    speed_m_s: float
    dt_s: float
    policy: StepPolicyKind  # for mode = "position_steps"
    fast: FastStepConfig
    move_speed_m_s: float  # taught moves (start, pick, place, check); approach and press at half


class HostTransport(StrEnum):
    """What carries the host commands to the controller (docs/robot-link.md)."""

    SERIAL = "serial"  # BSC blocks over RS-232: the JRC, and every controller of its family
    ETHERNET = "ethernet"  # the Ethernet server function of DX100 and later controllers, over TCP


@dataclass(frozen=True)
class JrcLineConfig:
    """The host link to a JRC-family controller: RS-232 (docs/robot-link.md, parameters
    RS030..RS038) or, on DX100 and later controllers, the Ethernet server over TCP.

    The defaults are the JRC's factory values; check them on the pendant before
    first use. timer_a_s: how long a sender waits for the answer to a control character
    or a block (RS034); over Ethernet, for the connection and each "OK:" of the server.
    timer_b_s: how long a receiver waits for a text to end, and the host for a command's
    reply (RS035); retry_1: repeats of a control character left
    unanswered (RS036); retry_2: repeats of a text the receiver refused with NAK (RS037).
    jwait_slice_s: a wait for the end of a motion is split into JWAITs this long, so a
    hold from the host (e-stop, watchdog) reaches the JRC within one slice.
    time_scale: an emulated JRC runs this many times faster than real time (the virtual
    cell writes it); 1, a real JRC. The host's cell clock undoes it.

    Over Ethernet (``transport``) the controller is ``host``:``tcp_port``, and as its
    server offers no JWAIT the end of a motion is found by reading its status (RSTATS)
    every ``status_poll_s`` of controller time; the serial line's keys do not apply.
    """

    port: str
    baud: int
    parity: str  # "even", "odd" or "none"
    data_bits: int
    stop_bits: int
    rtscts: bool
    timer_a_s: float
    timer_b_s: float
    retry_1: int
    retry_2: int
    jwait_slice_s: float
    time_scale: float = 1.0
    transport: HostTransport = HostTransport.SERIAL
    host: str = ""
    tcp_port: int = 80
    status_poll_s: float = 0.05

    @property
    def address(self) -> str:
        """Where the controller is: the serial device, or host:port."""
        return f"{self.host}:{self.tcp_port}" if self.transport is HostTransport.ETHERNET else self.port

    def in_use(self) -> dict[str, Any]:
        """The settings its transport reads (an Ethernet line's serial fields are defaults nothing reads)."""
        foreign = _SERIAL_FIELDS if self.transport is HostTransport.ETHERNET else _ETHERNET_FIELDS
        return {name: value for name, value in vars(self).items() if name not in foreign}

    def on_ethernet(self, host: str, tcp_port: int) -> JrcLineConfig:
        """This line's timers and time scale, to the Ethernet server at host:tcp_port."""
        return replace(self, transport=HostTransport.ETHERNET, host=host, tcp_port=tcp_port, port="")

    @property
    def bits_per_character(self) -> int:
        """Start bit, data bits, parity bit, stop bits: what one byte costs on the wire."""
        return 1 + self.data_bits + (self.parity != "none") + self.stop_bits

    def wire_time_s(self, n_bytes: int) -> float:
        """How long n_bytes take on the line at the configured baud rate."""
        return n_bytes * self.bits_per_character / self.baud


class PlcTransport(StrEnum):
    """What carries the PLC handshake's signals ([line.plc] transport, docs/plc.md)."""

    MODBUS = "modbus"  # a Modbus TCP server the controller serves: the PLC, its client, writes coils and reads discrete inputs
    JRC_IO = "jrc_io"  # the JRC's I/O lines: inputs the host reads, network inputs it writes (a ladder copies them out)


@dataclass(frozen=True)
class PlcInputMap:
    """Where the PLC's signals to the cell are: coils (Modbus) or JRC input addresses (byte.bit).
    ``job_bits``: the job number's bits, least significant first."""

    start: int
    part_present: int
    reset: int
    job_bits: tuple[int, ...]

    def addresses(self) -> tuple[int, ...]:
        """Every input's address: start, part_present, reset, then the job bits."""
        return (self.start, self.part_present, self.reset, *self.job_bits)


@dataclass(frozen=True)
class PlcOutputMap:
    """Where the cell's signals to the PLC are: discrete inputs (Modbus) or JRC network inputs
    (byte.bit) that the controller's ladder copies to the outputs wired to the PLC."""

    ready: int
    busy: int
    done: int
    ok: int
    not_ok: int
    fault: int

    def addresses(self) -> tuple[int, ...]:
        """Every output's address, in the order of the fields."""
        return (self.ready, self.busy, self.done, self.ok, self.not_ok, self.fault)


@dataclass(frozen=True)
class PlcConfig:
    """[line.plc]: the PLC handshake (docs/plc.md). ``jobs``: (job number, job name) pairs;
    ``poll_period_s``: how often the handshake reads its inputs and writes its outputs.
    Modbus only: the server's ``host`` and ``port`` (0: any free one), and the part ID's
    holding registers (``part_id_register``, None: the PLC gives none; two ASCII characters
    a register)."""

    transport: PlcTransport
    inputs: PlcInputMap
    outputs: PlcOutputMap
    jobs: tuple[tuple[int, str], ...]
    poll_period_s: float = 0.05
    host: str = "127.0.0.1"
    port: int = 5020
    part_id_register: int | None = None
    part_id_registers: int = 10

    def job_name(self, number: int) -> str | None:
        """The job the PLC's job number selects, None when [line.plc.jobs] has no such number."""
        return dict(self.jobs).get(number)


@dataclass(frozen=True)
class SafetyConfig:
    """The limits the safety layer (core/robot/safety.py) puts on every move.

    workspace_min_m / workspace_max_m: a box in the robot base frame that the flange and
    every tool frame (camera, laser, vacuum cup) must stay in; max_step_m / max_step_rad:
    the largest translation and rotation of one move; max_speed_m_s: the fastest linear
    speed a move may ask for; joint_margin_rad: how close to a joint limit the IK solution
    of a target may come; watchdog_s: how long the camera or the robot link may stay
    quiet during a servo before the robot is held.
    """

    workspace_min_m: Matrix
    workspace_max_m: Matrix
    max_step_m: float
    max_step_rad: float
    max_speed_m_s: float
    joint_margin_rad: float
    watchdog_s: float


@dataclass(frozen=True)
class RecordingRetention:
    """[recordings]: which runs' recordings the data folder keeps. After each run the oldest
    are removed first until at most ``keep_runs`` recordings and ``max_bytes`` remain; the
    runs themselves stay on record, their recording marked removed.

    The default bounds the recordings at 20 GB: on a 64 GB disk a cell recording camera
    images (about 1.7 MB a run) runs for months, its oldest recordings making room.
    """

    keep_runs: int = 2000
    max_bytes: int = 20 * 10**9


# What [recordings] accepts: one run's recording at least, and no more than a large disk.
MAX_KEEP_RUNS = 10_000_000
MAX_RECORDINGS_GB = 100_000.0


@dataclass(frozen=True)
class SimulationConfig:
    """The plant: the true cell and the noise a real one has."""

    seed: int
    truth: CellModel
    scene: Scene
    board: LaidBoard | None  # where the true board lies when laid; None without a [board]
    pixel_noise_px: float
    repeatability_m: float
    repeatability_rad: float
    joint_placement_error_m: float
    joint_placement_error_rad: float


@dataclass(frozen=True)
class CellConfig:
    source: str
    arm: str
    home_q: Matrix
    nominal: CellModel
    motion: MotionConfig
    simulation: SimulationConfig | None  # None: the file describes no simulated plant (a real cell's may not)
    robot_backend: str  # "sim" (the kinematic simulator) or "jrc" (the serial link)
    jrc: JrcLineConfig
    safety: SafetyConfig
    camera_source: CameraSourceConfig = CameraSourceConfig("simulated")
    vacuum_device: VacuumDeviceConfig = VacuumDeviceConfig("simulated")
    # [fixture] url: a test cell's part feeder and gauge (the virtual cell's), which can
    # present a new part; None on a production cell, where parts arrive by hand or conveyor.
    fixture_url: str | None = None
    board: BoardConfig | None = None  # [board]: None when the file names no calibration board
    commissioning: CommissioningRecord | None = None  # [commissioning]: None until the cell is commissioned
    # [metal_part] pose: where the cell's metal part stands as measured on the cell (its
    # pocket floor's centre); None when the file does not say. Teaching draws it and checks
    # a place pose against its pocket; the simulator's own is [simulation.scene].
    metal_part: MetalPart | None = None
    recordings: RecordingRetention = RecordingRetention()
    plc: PlcConfig | None = None  # [line.plc]: the PLC handshake, None without one
    line: LineConfig = LineConfig()  # [line]: the OPC UA server and the metrics endpoint (core/cell/line.py)

    def plant(self) -> SimulationConfig:
        """The [simulation] table, for code that simulates this cell; ConfigError when the file has none."""
        if self.simulation is None:
            raise ConfigError(f"{self.source}: no [simulation] table: this file describes no plant to simulate")
        return self.simulation

    @property
    def real(self) -> bool:
        """A real cell: its camera is not the simulator's (and, checked on load, neither are its robot and cup)."""
        return self.camera_source.real


class _Table:
    """Reads one TOML table, checking every value and refusing keys it does not know."""

    def __init__(self, data: Any, path: str, source: str) -> None:
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: {path} must be a table, got {data!r}")
        self._data, self._path, self._source = data, path, source
        self._used: set[str] = set()

    def _key(self, key: str) -> str:
        return f"{self._path}.{key}" if self._path else key

    def fail(self, key: str, value: Any, why: str) -> ConfigError:
        return ConfigError(f"{self._source}: {self._key(key)} = {value!r}: {why}")

    def _raw(self, key: str, default: Any) -> Any:
        self._used.add(key)
        if key in self._data:
            return self._data[key]
        if default is None:
            raise ConfigError(f"{self._source}: missing key {self._key(key)}")
        return default

    def number(
        self, key: str, default: float | None = None, *, check: Callable[[float], bool] | None = None, why: str = ""
    ) -> float:
        value = self._raw(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(key, value, "must be a finite number")
        if check is not None and not check(float(value)):
            raise self.fail(key, value, why)
        return float(value)

    def integer(self, key: str, default: int | None = None) -> int:
        value = self._raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(key, value, "must be an integer")
        return value

    def text(self, key: str, default: str | None = None) -> str:
        value = self._raw(key, default)
        if not isinstance(value, str) or not value:
            raise self.fail(key, value, "must be a non-empty string")
        return value

    def flag(self, key: str, default: bool) -> bool:
        value = self._raw(key, default)
        if not isinstance(value, bool):
            raise self.fail(key, value, "must be true or false")
        return value

    def choice(self, key: str, options: Sequence[str], default: str | None = None) -> str:
        value = self._raw(key, default)
        if value not in options:
            raise self.fail(key, value, f"must be one of {', '.join(options)}")
        return value

    def vector(self, key: str, length: int | None, default: Sequence[float] | None = None) -> Matrix:
        """A list of finite numbers, of the given length or of any non-zero length if None."""
        value = self._raw(key, default)
        ok = (
            isinstance(value, list)
            and (len(value) == length if length is not None else len(value) > 0)
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value)
        )
        if not ok:
            raise self.fail(key, value, f"must be a list of {length or 'one or more'} finite numbers")
        return np.array(value, dtype=float)

    def pose(self, key: str, default: Sequence[float] | None = None) -> Matrix:
        """A pose [X, Y, Z, phi, theta, psi] in mm and degrees, returned as a 4x4 in m."""
        return matrix_from_pose(pose_from_mm_deg(self.vector(key, 6, default)))

    def table(self, key: str) -> _Table:
        self._used.add(key)
        return _Table(self._data.get(key, {}), self._key(key), self._source)

    def finish(self) -> None:
        unknown = sorted(set(self._data) - self._used)
        if unknown:
            raise ConfigError(f"{self._source}: unknown key {self._key(unknown[0])}")


def _positive(v: float) -> bool:
    return v > 0.0


def _non_negative(v: float) -> bool:
    return v >= 0.0


def _camera(t: _Table) -> CameraModel:
    """[camera]: the intrinsics of Table 3-1 and an OpenCV distortion (k1 k2 p1 p2 k3).

    A data sheet gives the focal length in mm and the pixel pitch; a calibration measures
    the focal lengths in pixels, ``focal_length_px = [fx, fy]``, which then replaces them.
    """
    focal = t.number("focal_length_mm", 6.0, check=_positive, why="must be positive")
    pixel = t.vector("pixel_size_mm", 2, [0.0074, 0.0074])
    if np.any(pixel <= 0):
        raise t.fail("pixel_size_mm", pixel.tolist(), "both sizes must be positive")
    principal = t.vector("principal_point_px", 2, [320.0, 240.0])
    size = t.vector("image_size_px", 2, [640, 480])
    if np.any(size < 1) or np.any(size != np.round(size)) or np.any(size > MAX_IMAGE_SIDE_PX):
        raise t.fail("image_size_px", size.tolist(), f"must be two whole numbers from 1 to {MAX_IMAGE_SIDE_PX}")
    distortion = Distortion(*t.vector("distortion", 5, [0.0] * 5))
    measured = "focal_length_px" in t._data
    focal_px = t.vector("focal_length_px", 2, [1.0, 1.0])
    if np.any(focal_px <= 0):
        raise t.fail("focal_length_px", focal_px.tolist(), "both focal lengths must be positive")
    t.finish()
    if measured:
        intrinsics = Intrinsics(
            float(focal_px[0]), float(focal_px[1]), float(principal[0]), float(principal[1]), int(size[0]), int(size[1])
        )
    else:
        intrinsics = Intrinsics.from_sensor(
            focal_length_m=focal / 1000.0,
            pixel_size_m=(pixel[0] / 1000.0, pixel[1] / 1000.0),
            principal_point_px=(float(principal[0]), float(principal[1])),
            image_size_px=(int(size[0]), int(size[1])),
        )
    return CameraModel(intrinsics, distortion)


def _cell_model(root: _Table) -> CellModel:
    """The [camera], [hand_eye], [laser] and [vacuum] tables."""
    camera = _camera(root.table("camera"))
    hand_eye = root.table("hand_eye")
    eMc = hand_eye.pose("eMc", [0.0] * 6)
    hand_eye.finish()
    laser = root.table("laser")
    cMl = laser.pose("cMl", [30.0, 0.0, 0.0, 0.0, -10.0, 0.0])
    laser.finish()
    vacuum = root.table("vacuum")
    eMv = vacuum.pose("eMv", [0.0, 60.0, 150.0, 0.0, 0.0, 0.0])
    vacuum.finish()
    return CellModel(camera=camera, eMc=eMc, laser=LaserPointer(cMl), eMv=eMv)


def _camera_source(t: _Table, base_dir: Path | None) -> CameraSourceConfig:
    """[camera.source]: only the keys of its kind are accepted, so a stray one is an error."""
    kind = t.choice("kind", CAMERA_SOURCES, "simulated")
    if kind == "capture":
        device = t._raw("device", None)
        if (
            isinstance(device, bool)
            or not isinstance(device, (int, str))
            or device == ""
            or (isinstance(device, int) and device < 0)
        ):
            raise t.fail("device", device, "must be a device index >= 0, or a video file, stream URL or pipeline")
        attempts = t.integer("reconnect_attempts", 3)
        if attempts < 0:
            raise t.fail("reconnect_attempts", attempts, "must be >= 0")
        buffered = t.integer("buffer_frames", 0)
        if buffered < 0:
            raise t.fail("buffer_frames", buffered, "must be >= 0")
        source = CameraSourceConfig(
            kind,
            device=device,
            reconnect_attempts=attempts,
            reconnect_delay_s=t.number("reconnect_delay_s", 0.5, check=_non_negative, why="must be >= 0"),
            loop=t.flag("loop", False),
            exposure_latency_s=t.number("exposure_latency_s", 0.0, check=_non_negative, why="must be >= 0"),
            buffer_frames=buffered,
        )
    elif kind == "folder":
        path = Path(t.text("path"))
        # A relative folder is read from the cell file's folder, where a dry run keeps its frames.
        if not path.is_absolute() and base_dir is not None:
            path = base_dir / path
        source = CameraSourceConfig(kind, path=path, pattern=t.text("pattern", "*.png"))
    else:
        source = CameraSourceConfig(kind)
    t.finish()
    return source


def _fixture_url(t: _Table) -> str | None:
    """[fixture] url: the http:// address of a test cell's fixture, if the cell has one."""
    if "url" not in t._data:
        t.finish()
        return None
    url = t.text("url")
    if not url.startswith(("http://", "https://")):
        raise t.fail("url", url, "must be an http:// address (the fixture's JSON port)")
    t.finish()
    return url.rstrip("/")


def _board(t: _Table) -> BoardConfig | None:
    """[board]: square side, inner corners and rough pose; None when the table is absent."""
    if not t._data:
        return None
    square = t.number("square_mm", None, check=_positive, why="must be positive") / 1000.0
    corners = t.vector("inner_corners", 2, None)
    if np.any(corners < 3) or np.any(corners != np.round(corners)) or corners[0] == corners[1]:
        raise t.fail(
            "inner_corners",
            corners.tolist(),
            "must be two different whole numbers >= 3 (columns, rows): a square board's quarter turns cannot be told apart",
        )
    board = BoardConfig(square, (int(corners[0]), int(corners[1])), t.pose("pose", None))
    t.finish()
    return board


def _metal_part(t: _Table) -> MetalPart | None:
    """[metal_part]: the pose of its pocket floor's centre (mm, deg); None when the table is absent."""
    if not t._data:
        return None
    part = MetalPart(t.pose("pose", None))
    if abs(part.bMp[2, 2]) < 1.0 - 1e-9:
        raise t.fail(
            "pose", t._data["pose"], "the pocket opens straight up: theta and psi must be 0 (phi turns it about the vertical)"
        )
    t.finish()
    return part


def _recordings(t: _Table) -> RecordingRetention:
    """[recordings]: keep_runs and max_gb, each bounded (a typo must not switch retention off)."""
    default = RecordingRetention()
    keep_runs = t.integer("keep_runs", default.keep_runs)
    if not 1 <= keep_runs <= MAX_KEEP_RUNS:
        raise t.fail("keep_runs", keep_runs, f"must be a whole number from 1 to {MAX_KEEP_RUNS}")
    max_gb = t.number(
        "max_gb",
        default.max_bytes / 1e9,
        check=lambda gb: 0.0 < gb <= MAX_RECORDINGS_GB,
        why=f"must be more than 0 and at most {MAX_RECORDINGS_GB:g} GB",
    )
    t.finish()
    return RecordingRetention(keep_runs, int(max_gb * 1e9))


def _commissioning(t: _Table, base_dir: Path | None) -> CommissioningRecord | None:
    """[commissioning]: the network's file and a free-form provenance table."""
    if not t._data:
        return None
    nn_path = None
    if "nn_file" in t._data:
        nn_path = Path(t.text("nn_file"))
        if not nn_path.is_absolute() and base_dir is not None:
            nn_path = base_dir / nn_path
    provenance = t._raw("provenance", {})
    if not isinstance(provenance, dict):
        raise t.fail("provenance", provenance, "must be a table")
    t.finish()
    return CommissioningRecord(nn_path, provenance)


def _io_address(t: _Table, key: str) -> int:
    value = t.integer(key)
    if value < 0 or value % 10 > 7:
        raise t.fail(key, value, "must be a byte.bit I/O address >= 0 whose last digit, the bit, is 0..7")
    return value


def _vacuum_device(t: _Table) -> VacuumDeviceConfig:
    device = t.choice("device", VACUUM_DEVICES, "simulated")
    if device == "jrc_io":
        vacuum = VacuumDeviceConfig(device, _io_address(t, "suction_output"), _io_address(t, "grip_input"))
    else:
        vacuum = VacuumDeviceConfig(device)
    t.finish()
    return vacuum


# [line.plc]'s limits: Modbus addresses are 16-bit; a job number of more than 16 bits is a typo.
MODBUS_ADDRESSES = (0, 65535)
MAX_JOB_BITS = 16
PLC_POLL_PERIOD_S = (0.005, 5.0)
MAX_PART_ID_REGISTERS = 32  # 64 characters, the store's longest part ID
_MODBUS_ONLY_KEYS = ("host", "port", "part_id_register", "part_id_registers")


def _plc(t: _Table) -> PlcConfig:
    transport = PlcTransport(t.choice("transport", tuple(PlcTransport)))
    if transport is PlcTransport.JRC_IO:
        for key in _MODBUS_ONLY_KEYS:
            if key in t._data:
                raise t.fail(key, t._data[key], 'has no meaning with transport = "jrc_io": remove it')
    inputs = _plc_inputs(t.table("inputs"), transport)
    outputs = _plc_outputs(t.table("outputs"), transport)
    low, high = PLC_POLL_PERIOD_S
    config = PlcConfig(
        transport,
        inputs,
        outputs,
        _plc_jobs(t.table("jobs"), len(inputs.job_bits)),
        poll_period_s=t.number("poll_period_s", 0.05, check=lambda v: low <= v <= high, why=f"must be {low:g} to {high:g} s"),
    )
    if transport is PlcTransport.MODBUS:
        port = t.integer("port", 5020)
        if not 0 <= port <= TCP_PORTS[1]:
            raise t.fail("port", port, f"a TCP port, 0 (any free one) to {TCP_PORTS[1]}")
        count = t.integer("part_id_registers", 10)
        if not 1 <= count <= MAX_PART_ID_REGISTERS:
            raise t.fail("part_id_registers", count, f"must be 1 to {MAX_PART_ID_REGISTERS} (two characters a register)")
        first = t.integer("part_id_register", -1)
        if first != -1 and not 0 <= first <= MODBUS_ADDRESSES[1] + 1 - count:
            raise t.fail(
                "part_id_register",
                first,
                f"must be 0 to {MODBUS_ADDRESSES[1] + 1 - count}, its {count} registers within 0..65535",
            )
        config = replace(
            config,
            host=t.text("host", "127.0.0.1"),
            port=port,
            part_id_register=None if first == -1 else first,
            part_id_registers=count,
        )
    t.finish()
    return config


def _plc_address(t: _Table, key: str, transport: PlcTransport, value: Any = None) -> int:
    """One signal's address: a Modbus coil or discrete input (0..65535), or a JRC byte.bit address."""
    value = t.integer(key) if value is None else value
    if isinstance(value, bool) or not isinstance(value, int):
        raise t.fail(key, value, "must be an integer")
    if transport is PlcTransport.JRC_IO and (value < 0 or value % 10 > 7):
        raise t.fail(key, value, "must be a byte.bit I/O address >= 0 whose last digit, the bit, is 0..7")
    if transport is PlcTransport.MODBUS and not MODBUS_ADDRESSES[0] <= value <= MODBUS_ADDRESSES[1]:
        raise t.fail(key, value, f"must be a Modbus address, {MODBUS_ADDRESSES[0]} to {MODBUS_ADDRESSES[1]}")
    return value


def _distinct(t: _Table, addresses: dict[str, int]) -> None:
    seen: dict[int, str] = {}
    for key, address in addresses.items():
        if address in seen:
            raise t.fail(key, address, f"is also {t._key(seen[address])}: each signal needs its own address")
        seen[address] = key


def _plc_inputs(t: _Table, transport: PlcTransport) -> PlcInputMap:
    bits = t._raw("job_bits", None)
    if not isinstance(bits, list) or not 1 <= len(bits) <= MAX_JOB_BITS:
        raise t.fail("job_bits", bits, f"must be a list of 1 to {MAX_JOB_BITS} addresses, least significant bit first")
    job_bits = tuple(_plc_address(t, "job_bits", transport, bit) for bit in bits)
    signals = {key: _plc_address(t, key, transport) for key in ("start", "part_present", "reset")}
    _distinct(t, {**signals, **{f"job_bits[{i}]": bit for i, bit in enumerate(job_bits)}})
    t.finish()
    return PlcInputMap(job_bits=job_bits, **signals)


def _plc_outputs(t: _Table, transport: PlcTransport) -> PlcOutputMap:
    signals = {key: _plc_address(t, key, transport) for key in ("ready", "busy", "done", "ok", "not_ok", "fault")}
    _distinct(t, signals)
    t.finish()
    return PlcOutputMap(**signals)


def _plc_jobs(t: _Table, n_bits: int) -> tuple[tuple[int, str], ...]:
    """[line.plc.jobs]: job number = "job name"; numbers the job bits can carry."""
    if not t._data:
        raise ConfigError(f'{t._source}: {t._path} is empty: give each job number its job, as 1 = "demo"')
    jobs = []
    for key in sorted(t._data):
        if not key.isdigit() or int(key) >= 2**n_bits:
            raise t.fail(key, t._data[key], f"the key must be a job number, 0 to {2**n_bits - 1} ({n_bits} job bits)")
        jobs.append((int(key), t.text(key)))
    t.finish()
    return tuple(sorted(jobs))


# The keys of the model tables that say how a device is wired rather than what the cell
# is: the control laws never read them and [simulation.truth.*] cannot override them.
_WIRING_KEYS = {"camera": ("source",), "vacuum": ("device", "suction_output", "grip_input")}


def _split_wiring(data: dict[str, Any]) -> tuple[dict[str, Any], dict[str, dict[str, Any]]]:
    """(the file without the wiring keys, the wiring keys of each model table)."""
    model, wiring = dict(data), {}
    for name, keys in _WIRING_KEYS.items():
        table = data.get(name, {})
        if isinstance(table, dict):
            model[name] = {k: v for k, v in table.items() if k not in keys}
            wiring[name] = {k: v for k, v in table.items() if k in keys}
    return model, wiring


def _check_devices(config: CellConfig) -> None:
    """The devices of one cell must belong together: a real camera films a real robot."""
    source, backend, vacuum = config.source, config.robot_backend, config.vacuum_device.device
    if config.real and backend != "jrc":
        raise ConfigError(
            f"{source}: robot.backend = {backend!r}: a cell with camera.source.kind = "
            f'{config.camera_source.kind!r} drives a real robot: set backend = "jrc"'
        )
    if config.real and vacuum == "simulated":
        raise ConfigError(
            f"{source}: vacuum.device = 'simulated': a cell with camera.source.kind = "
            f'{config.camera_source.kind!r} has no simulator: choose "jrc_io" or "none"'
        )
    if vacuum == "jrc_io" and backend != "jrc":
        raise ConfigError(
            f"{source}: vacuum.device = 'jrc_io': the vacuum on the JRC's I/O needs robot.backend = \"jrc\", not {backend!r}"
        )
    if config.plc is not None and config.plc.transport is PlcTransport.JRC_IO:
        _check_plc_on_jrc(config.plc, config)


def _plc_input_signals(plc: PlcConfig) -> dict[str, int]:
    """The PLC's input signals by their keys' names: start, ..., job_bits[0], ..."""
    inputs = plc.inputs
    named = {"start": inputs.start, "part_present": inputs.part_present, "reset": inputs.reset}
    return {**named, **{f"job_bits[{i}]": bit for i, bit in enumerate(inputs.job_bits)}}


def _check_plc_on_jrc(plc: PlcConfig, config: CellConfig) -> None:
    """The handshake on the JRC's I/O needs the JRC, and lines of its own beside the cup's."""
    if config.robot_backend != "jrc":
        raise ConfigError(
            f'{config.source}: line.plc.transport = "jrc_io": the PLC on the JRC\'s I/O needs robot.backend = "jrc", '
            f"not {config.robot_backend!r}"
        )
    outputs = vars(plc.outputs)
    for name, address in _plc_input_signals(plc).items():
        if address in outputs.values():
            raise ConfigError(f"{config.source}: line.plc.inputs.{name} = {address}: it is also a [line.plc.outputs] address")
    if config.vacuum_device.device == "jrc_io":
        suction, grip = config.vacuum_device.jrc_io()
        for name, address in vars(plc.outputs).items():
            if address == suction:
                raise ConfigError(f"{config.source}: line.plc.outputs.{name} = {address}: it is vacuum.suction_output")
        for name, address in _plc_input_signals(plc).items():
            if address == grip:
                raise ConfigError(f"{config.source}: line.plc.inputs.{name} = {address}: it is vacuum.grip_input")


# How far the true board may lie from the table's plane: it is a printed sheet on it.
_SHEET_ON_TABLE_M = 1e-5
_SHEET_LEVEL_RAD = math.radians(0.01)


def _scene(t: _Table, board: BoardConfig | None) -> tuple[Scene, LaidBoard | None]:
    """The scene as the plant starts (no board laid), and the board where it lies when laid:
    ``board_pose``, or the [board] pose by default; it must lie flat on the table."""
    table_height = t.number("table_height_mm", 0.0) / 1000.0
    cube = Cube(t.pose("object_pose", None), t.number("cube_side_mm", 20.0, check=_positive, why="must be positive") / 1000.0)
    part = MetalPart(t.pose("metal_part_pose", None))
    laid = None
    if "board_pose" in t._data and board is None:
        raise t.fail("board_pose", t._data["board_pose"], "needs a [board] table (square_mm, inner_corners, pose)")
    if board is not None:
        given = "board_pose" in t._data
        bMboard = t.pose("board_pose") if given else board.bMboard
        tilt = math.acos(min(1.0, float(bMboard[2, 2])))
        if abs(bMboard[2, 3] - table_height) > _SHEET_ON_TABLE_M or tilt > _SHEET_LEVEL_RAD:
            key = "board_pose" if given else "board_pose (not given: the [board] pose)"
            raise t.fail(
                key,
                t._data.get("board_pose", "[board] pose"),
                f"the board is a sheet lying on the table: its z ({1000.0 * bMboard[2, 3]:g} mm) must be "
                f"table_height_mm = {1000.0 * table_height:g} and it must lie level (theta = psi = 0; "
                f"it is tilted {math.degrees(tilt):.3g} deg)",
            )
        laid = LaidBoard(bMboard, board.square_m, board.inner_corners)
    t.finish()
    return Scene(table_height, cube, part), laid


def _motion(t: _Table, safety: SafetyConfig) -> MotionConfig:
    policy = StepPolicyKind(t.choice("policy", tuple(StepPolicyKind), StepPolicyKind.THESIS))
    motion = MotionConfig(
        mode=t.choice("mode", ("position_steps", "velocity"), "position_steps"),
        divide_factor=t.number("divide_factor", 50.0, check=lambda v: v >= 1.0, why="must be at least 1"),
        sampling_period_s=t.number("sampling_period_s", 2.0, check=_positive, why="must be positive"),
        speed_m_s=t.number("speed_mm_s", 50.0, check=_positive, why="must be positive") / 1000.0,
        dt_s=t.number("dt_s", 0.05, check=_positive, why="must be positive"),
        policy=policy,
        fast=_fast_steps(t.table("fast"), safety if policy is StepPolicyKind.FAST else None),
        # A taught move faster than [safety] allows is refused when it is sent, as a jog's is.
        move_speed_m_s=t.number("move_speed_mm_s", 50.0, check=_positive, why="must be positive") / 1000.0,
    )
    t.finish()
    return motion


def _fast_steps(t: _Table, safety: SafetyConfig | None) -> FastStepConfig:
    """[motion.fast]. For the fast policy (``safety`` given) a step or speed beyond the
    [safety] limits is refused here: the safety layer would refuse every such step mid-servo."""
    step_mm, step_deg, speed_mm_s = (
        (1000.0 * safety.max_step_m, math.degrees(safety.max_step_rad), 1000.0 * safety.max_speed_m_s)
        if safety
        else (math.inf,) * 3
    )
    fast = FastStepConfig(
        max_step_m=_within(t, "max_step_mm", 40.0, step_mm, "max_step_mm") / 1000.0,
        max_step_rad=math.radians(_within(t, "max_step_deg", 10.0, step_deg, "max_step_deg")),
        speed_m_s=_within(t, "speed_mm_s", 100.0, speed_mm_s, "max_speed_mm_s") / 1000.0,
    )
    t.finish()
    return fast


def _within(t: _Table, key: str, default: float, limit: float, safety_key: str) -> float:
    """A positive number at most the [safety] limit ``safety_key`` (``limit``), which would refuse more."""
    value = t.number(key, default, check=_positive, why="must be positive")
    if value > limit:
        raise t.fail(key, value, f'exceeds [safety] {safety_key} = {limit:g} (policy = "fast"), which refuses such a move')
    return value


# The baud rates of RS033 (150 .. 19200).
BAUD_RATES = (150, 300, 600, 1200, 2400, 4800, 9600, 19200)


def _integer_in(t: _Table, key: str, default: int, options: Sequence[int]) -> int:
    value = t.integer(key, default)
    if value not in options:
        raise t.fail(key, value, f"must be one of {', '.join(map(str, options))}")
    return value


# The fields of JrcLineConfig only one transport reads.
_SERIAL_FIELDS = ("port", "baud", "parity", "data_bits", "stop_bits", "rtscts", "retry_1", "retry_2", "jwait_slice_s")
_ETHERNET_FIELDS = ("host", "tcp_port", "status_poll_s")
# The [jrc] keys only one transport has; the other refuses them by name.
SERIAL_ONLY_KEYS = ("baud", "parity", "data_bits", "stop_bits", "rtscts", "retry_1", "retry_2", "jwait_slice_s")
ETHERNET_ONLY_KEYS = ("host", "status_poll_s")
TCP_PORTS = (1, 65535)


def _jrc(t: _Table) -> JrcLineConfig:
    transport = HostTransport(t.choice("transport", tuple(HostTransport), HostTransport.SERIAL))
    foreign = ETHERNET_ONLY_KEYS if transport is HostTransport.SERIAL else SERIAL_ONLY_KEYS
    for key in foreign:
        if key in t._data:
            raise t.fail(key, t._data[key], f'has no meaning with transport = "{transport}": remove it')
    line = _ethernet_line(t) if transport is HostTransport.ETHERNET else _serial_line(t)
    t.finish()
    return line


def _line_timers(t: _Table) -> tuple[float, float, float]:
    """timer_a_s, timer_b_s and time_scale, which both transports have."""
    return (
        t.number("timer_a_s", 3.0, check=_positive, why="must be positive"),
        t.number("timer_b_s", 20.0, check=_positive, why="must be positive"),
        t.number("time_scale", 1.0, check=lambda v: 1.0 <= v <= 1000.0, why="must be 1 (a real JRC) to 1000"),
    )


def _serial_line(t: _Table) -> JrcLineConfig:
    retries = {}
    for key, default in (("retry_1", 10), ("retry_2", 3)):
        retries[key] = t.integer(key, default)
        if retries[key] < 0:
            raise t.fail(key, retries[key], "must be >= 0")
    timer_a_s, timer_b_s, time_scale = _line_timers(t)
    return JrcLineConfig(
        port=t.text("port", "/dev/ttyS0"),
        baud=_integer_in(t, "baud", 9600, BAUD_RATES),
        parity=t.choice("parity", ("even", "odd", "none"), "even"),
        data_bits=_integer_in(t, "data_bits", 8, (7, 8)),
        stop_bits=_integer_in(t, "stop_bits", 1, (1, 2)),
        rtscts=t.flag("rtscts", True),
        timer_a_s=timer_a_s,
        timer_b_s=timer_b_s,
        retry_1=retries["retry_1"],
        retry_2=retries["retry_2"],
        jwait_slice_s=t.number("jwait_slice_s", 0.5, check=_positive, why="must be positive"),
        time_scale=time_scale,
    )


def _ethernet_line(t: _Table) -> JrcLineConfig:
    """[jrc] with transport = "ethernet": the controller's address; the serial fields keep
    their defaults, which nothing reads."""
    tcp_port = t.integer("port", 80)
    if not TCP_PORTS[0] <= tcp_port <= TCP_PORTS[1]:
        raise t.fail("port", tcp_port, f"a TCP port, {TCP_PORTS[0]} to {TCP_PORTS[1]} (the Ethernet server listens on 80)")
    timer_a_s, timer_b_s, time_scale = _line_timers(t)
    return JrcLineConfig(
        port="",
        baud=9600,
        parity="even",
        data_bits=8,
        stop_bits=1,
        rtscts=True,
        timer_a_s=timer_a_s,
        timer_b_s=timer_b_s,
        retry_1=0,
        retry_2=0,
        jwait_slice_s=0.5,
        time_scale=time_scale,
        transport=HostTransport.ETHERNET,
        host=t.text("host"),
        tcp_port=tcp_port,
        status_poll_s=t.number("status_poll_s", 0.05, check=_positive, why="must be positive"),
    )


def _safety(t: _Table) -> SafetyConfig:
    low = t.vector("workspace_min_mm", 3, [-650.0, -400.0, -170.0])
    high = t.vector("workspace_max_mm", 3, [-150.0, 400.0, 450.0])
    if np.any(low >= high):
        raise t.fail("workspace_max_mm", high.tolist(), f"must exceed workspace_min_mm {low.tolist()} on every axis")
    safety = SafetyConfig(
        workspace_min_m=low / 1000.0,
        workspace_max_m=high / 1000.0,
        max_step_m=t.number("max_step_mm", 50.0, check=_positive, why="must be positive") / 1000.0,
        max_step_rad=math.radians(t.number("max_step_deg", 15.0, check=_positive, why="must be positive")),
        max_speed_m_s=t.number("max_speed_mm_s", 250.0, check=_positive, why="must be positive") / 1000.0,
        joint_margin_rad=math.radians(t.number("joint_margin_deg", 0.0, check=_non_negative, why="must be >= 0")),
        watchdog_s=t.number(
            "watchdog_s",
            5.0,
            check=lambda s: 0.0 < s <= MAX_WATCHDOG_S,
            why=f"must be more than 0 and at most {MAX_WATCHDOG_S:g} s",
        ),
    )
    t.finish()
    return safety


_MODEL_TABLES = ("camera", "hand_eye", "laser", "vacuum")


def _truth_tables(data: dict[str, Any], truth: Any, source: str) -> dict[str, Any]:
    """The nominal model tables with [simulation.truth.*] values laid over them."""
    truth_table = _Table(truth, "simulation.truth", source)
    merged = {}
    for name in _MODEL_TABLES:
        override = truth_table.table(name)._data
        merged[name] = {**data.get(name, {}), **override}
    truth_table.finish()
    return merged


def _simulation(t: _Table, truth: CellModel, board: BoardConfig | None) -> SimulationConfig:
    t.table("truth")  # parsed by _truth_tables; marked as known here
    scene, laid_board = _scene(t.table("scene"), board)
    simulation = SimulationConfig(
        seed=t.integer("seed", 0),
        truth=truth,
        scene=scene,
        board=laid_board,
        pixel_noise_px=t.number("pixel_noise_px", 0.0, check=_non_negative, why="must be >= 0"),
        repeatability_m=t.number("repeatability_mm", 0.0, check=_non_negative, why="must be >= 0") / 1000.0,
        repeatability_rad=math.radians(t.number("repeatability_deg", 0.0, check=_non_negative, why="must be >= 0")),
        joint_placement_error_m=t.number("joint_placement_error_mm", 0.0, check=_non_negative, why="must be >= 0") / 1000.0,
        joint_placement_error_rad=math.radians(
            t.number("joint_placement_error_deg", 0.0, check=_non_negative, why="must be >= 0")
        ),
    )
    t.finish()
    return simulation


def parse_cell(data: dict[str, Any], source: str = "<cell>", base_dir: Path | None = None) -> CellConfig:
    """Build a CellConfig from parsed TOML, validating every key.

    The truth is parsed by the same code as the nominal model, from the nominal tables
    with the [simulation.truth.*] overrides laid over them, so an error in an override
    is reported under the nominal key it overrides. ``base_dir``: the folder relative
    paths in the file are read from (the cell file's own).
    """
    from vservo.robot_models.loader import ARM_NAMES, joint_limits

    data, wiring = _split_wiring(data)
    root = _Table(data, "", source)
    robot = root.table("robot")
    arm = robot.choice("arm", ARM_NAMES, "upj")
    home_deg = robot.vector("home_joints_deg", None, None)
    lower, upper = np.degrees(joint_limits(arm))
    if home_deg.shape != lower.shape:
        raise robot.fail("home_joints_deg", home_deg.tolist(), f"{home_deg.size} values, the {arm} arm has {lower.size} joints")
    if np.any(home_deg < lower) or np.any(home_deg > upper):
        limits = ", ".join(f"[{lo:.1f}, {hi:.1f}]" for lo, hi in zip(lower, upper))
        raise robot.fail("home_joints_deg", home_deg.tolist(), f"beyond the {arm}'s joint limits (deg) {limits}")
    home_q = np.deg2rad(home_deg)
    backend = robot.choice("backend", ROBOT_BACKENDS, "sim")
    robot.finish()

    nominal = _cell_model(root)
    simulation_data = data.get("simulation", {})
    truth_data = simulation_data.get("truth", {}) if isinstance(simulation_data, dict) else {}
    truth = _cell_model(_Table(_truth_tables(data, truth_data, source), "", f"{source} [simulation.truth]"))
    board = _board(root.table("board"))
    # A controller's file for a real cell may leave the plant out: only a simulator reads it.
    simulation = _simulation(root.table("simulation"), truth, board) if "simulation" in data else None
    jrc = _jrc(root.table("jrc"))
    safety = _safety(root.table("safety"))
    motion = _motion(root.table("motion"), safety)
    fixture_url = _fixture_url(root.table("fixture"))
    commissioning = _commissioning(root.table("commissioning"), base_dir)
    metal_part = _metal_part(root.table("metal_part"))
    recordings = _recordings(root.table("recordings"))
    line_table = root.table("line")
    plc = _plc(line_table.table("plc")) if "plc" in line_table._data else None
    line = parse_line(line_table, base_dir)
    root.finish()
    camera_source = _camera_source(_Table(wiring.get("camera", {}), "camera", source).table("source"), base_dir)
    vacuum_device = _vacuum_device(_Table(wiring.get("vacuum", {}), "vacuum", source))
    config = CellConfig(
        source,
        arm,
        home_q,
        nominal,
        motion,
        simulation,
        backend,
        jrc,
        safety,
        camera_source,
        vacuum_device,
        fixture_url,
        board,
        commissioning,
        metal_part,
        recordings,
        plc,
        line,
    )
    _check_devices(config)
    return config


def model_with_truth(data: dict[str, Any], truth: dict[str, Any], source: str = "<cell>") -> CellModel:
    """The model of a cell file's tables with ``truth`` ([simulation.truth.*] tables, as a
    virtual cell's --truth file holds them) laid over its nominal ones."""
    data, _ = _split_wiring(data)
    return _cell_model(_Table(_truth_tables(data, truth, source), "", f"{source} [simulation.truth]"))


def read_cell_bytes(path: str | Path | None = None) -> tuple[bytes, str]:
    """A cell file's bytes (what a study snapshot hashes) and its name; ``None`` reads the shipped cell."""
    if path is None:
        return resources.files("vservo.static").joinpath(DEFAULT_CELL).read_bytes(), f"static/{DEFAULT_CELL}"
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"cell file not found: {path}")
    return path.read_bytes(), str(path)


def read_cell_data(path: str | Path | None = None) -> tuple[dict[str, Any], str]:
    """The parsed TOML of a cell file and its name; ``None`` reads the shipped cell."""
    raw, source = read_cell_bytes(path)
    try:
        return tomllib.loads(raw.decode("utf-8")), source
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{source}: not a text file (byte {exc.start} is not UTF-8)") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None


def write_thesis_policy_cell(folder: Path) -> Path:
    """The shipped cell file on the thesis's step policy ([motion] policy = "thesis"),
    written into ``folder``: its servo takes hundreds of cycles, one per sampling period,
    long enough to watch a run or act in its middle (the shipped fast policy's takes a few)."""
    shipped = read_cell_bytes()[0].decode("utf-8")
    thesis = shipped.replace('\npolicy = "fast"', '\npolicy = "thesis"')
    if thesis == shipped:
        raise ConfigError('the shipped cell file names no [motion] policy = "fast"')
    path = Path(folder) / "thesis-policy-cell.toml"
    path.write_text(thesis)
    return path


def with_truth(cell_tables: dict[str, Any], truth_file: dict[str, Any] | None) -> dict[str, Any]:
    """The cell's tables with the truth file's [simulation.truth.*] in place of its own,
    and its [simulation.scene] board_pose (where the board truly lies), if it has one."""
    tables = copy.deepcopy(cell_tables)
    if truth_file is not None:
        simulation = truth_file.get("simulation", {})
        truth = simulation.get("truth")
        if not isinstance(truth, dict) or not truth:
            raise ConfigError("the truth file has no [simulation.truth.*] tables: it says nothing about the true cell")
        tables.setdefault("simulation", {})["truth"] = copy.deepcopy(truth)
        board_pose = simulation.get("scene", {}).get("board_pose")
        if board_pose is not None:
            tables["simulation"].setdefault("scene", {})["board_pose"] = copy.deepcopy(board_pose)
    return tables


def read_cell_data_with_truth(cell: str | Path | None, truth: str | Path | None) -> tuple[dict[str, Any], str]:
    """The ``cell`` file's tables (the shipped cell by default) with the ``truth`` file's truth
    laid over them (``--truth`` of ``vservo virtual-cell``, ``simulate`` and ``montecarlo``)."""
    tables, source = read_cell_data(cell)
    if truth is None:
        return with_truth(tables, None), source
    try:
        return with_truth(tables, read_cell_data(truth)[0]), f"{source} with the truth of {truth}"
    except ConfigError as exc:
        raise ConfigError(f"--truth {truth}: {exc}") from None


def load_cell(path: str | Path | None = None) -> CellConfig:
    """Load a cell file; ``None`` loads the default cell shipped in ``static/``."""
    data, source = read_cell_data(path)
    return parse_cell(data, source, None if path is None else Path(path).parent)
