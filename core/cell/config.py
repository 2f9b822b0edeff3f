"""The cell configuration file (TOML): the nominal cell, its layout, and the simulated truth.

One file describes a cell. Its nominal sections (robot, camera, hand_eye, laser,
vacuum, motion) are what control laws and calibrations may use; ``[jrc]`` holds the
serial line to a JRC and ``[safety]`` the limits on every move; ``[simulation]``
describes the plant the simulator plays: its seed and noise, ``[simulation.scene]``
(where the table, cube and metal part really are) and ``[simulation.truth.*]`` tables
that override nominal values with what the cell really is (the robustness test of
Table 5-3 is such a file).

Poses are written as [X, Y, Z, phi, theta, psi] in mm and degrees with
R = Rz(phi) Ry(theta) Rx(psi) (eq. 2-13), the form of the thesis tables; they are
converted to SI once, here. Every error names the file, the key and the bad value.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.cell.kinematics import ToolMount
from vservo.core.cell.scene import Cube, MetalPart, Scene
from vservo.core.geometry.camera import CameraModel, Distortion, Intrinsics
from vservo.core.geometry.laser import LaserPointer
from vservo.core.geometry.spatial import Matrix, matrix_from_pose, pose_from_mm_deg

DEFAULT_CELL = "cell.toml"


class ConfigError(ValueError):
    """A cell configuration that cannot be used; the message names the key and value."""


ROBOT_BACKENDS = ("sim", "jrc")  # the kinematic simulator, the JRC link

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
class MotionConfig:
    """How moves reach the robot (section 5.3: the JRC takes one target at a time)."""

    mode: str  # "position_steps" (JRC style) or "velocity"
    divide_factor: float
    sampling_period_s: float
    speed_m_s: float
    dt_s: float


@dataclass(frozen=True)
class JrcLineConfig:
    """The RS-232 host link to a JRC (docs/robot-link.md, parameters RS030..RS038).

    The defaults are the JRC's factory values; check them on the pendant before
    first use. timer_a_s: how long a sender waits for the answer to a control character
    or a block (RS034); timer_b_s: how long a receiver waits for a text to end, and the
    host for a command's reply (RS035); retry_1: repeats of a control character left
    unanswered (RS036); retry_2: repeats of a text the receiver refused with NAK (RS037).
    jwait_slice_s: a wait for the end of a motion is split into JWAITs this long, so a
    hold from the host (e-stop, watchdog) reaches the JRC within one slice.
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

    @property
    def bits_per_character(self) -> int:
        """Start bit, data bits, parity bit, stop bits: what one byte costs on the wire."""
        return 1 + self.data_bits + (self.parity != "none") + self.stop_bits

    def wire_time_s(self, n_bytes: int) -> float:
        """How long n_bytes take on the line at the configured baud rate."""
        return n_bytes * self.bits_per_character / self.baud


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
class SimulationConfig:
    """The plant: the true cell and the noise a real one has."""

    seed: int
    truth: CellModel
    scene: Scene
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
    simulation: SimulationConfig
    robot_backend: str  # "sim" (the kinematic simulator) or "jrc" (the serial link)
    jrc: JrcLineConfig
    safety: SafetyConfig


class _Table:
    """Reads one TOML table, checking every value and refusing keys it does not know."""

    def __init__(self, data: Any, path: str, source: str) -> None:
        if not isinstance(data, dict):
            raise ConfigError(f"{source}: {path} must be a table, got {data!r}")
        self._data, self._path, self._source, self._used = data, path, source, set()

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

    def number(self, key: str, default: float | None = None, *, check: Callable[[float], bool] | None = None,
               why: str = "") -> float:
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
    """[camera]: the intrinsics of Table 3-1 and an OpenCV distortion (k1 k2 p1 p2 k3)."""
    focal = t.number("focal_length_mm", 6.0, check=_positive, why="must be positive")
    pixel = t.vector("pixel_size_mm", 2, [0.0074, 0.0074])
    if np.any(pixel <= 0):
        raise t.fail("pixel_size_mm", pixel.tolist(), "both sizes must be positive")
    principal = t.vector("principal_point_px", 2, [320.0, 240.0])
    size = t.vector("image_size_px", 2, [640, 480])
    if np.any(size < 1) or np.any(size != np.round(size)):
        raise t.fail("image_size_px", size.tolist(), "must be two positive whole numbers")
    distortion = Distortion(*t.vector("distortion", 5, [0.0] * 5))
    t.finish()
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


def _scene(t: _Table) -> Scene:
    table_height = t.number("table_height_mm", 0.0) / 1000.0
    cube = Cube(t.pose("object_pose", None), t.number("cube_side_mm", 20.0, check=_positive,
                                                        why="must be positive") / 1000.0)
    part = MetalPart(t.pose("metal_part_pose", None))
    t.finish()
    return Scene(table_height, cube, part)


def _motion(t: _Table) -> MotionConfig:
    motion = MotionConfig(
        mode=t.choice("mode", ("position_steps", "velocity"), "position_steps"),
        divide_factor=t.number("divide_factor", 50.0, check=lambda v: v >= 1.0, why="must be at least 1"),
        sampling_period_s=t.number("sampling_period_s", 2.0, check=_positive, why="must be positive"),
        speed_m_s=t.number("speed_mm_s", 50.0, check=_positive, why="must be positive") / 1000.0,
        dt_s=t.number("dt_s", 0.05, check=_positive, why="must be positive"),
    )
    t.finish()
    return motion


# The baud rates of RS033 (150 .. 19200).
BAUD_RATES = (150, 300, 600, 1200, 2400, 4800, 9600, 19200)


def _integer_in(t: _Table, key: str, default: int, options: Sequence[int]) -> int:
    value = t.integer(key, default)
    if value not in options:
        raise t.fail(key, value, f"must be one of {', '.join(map(str, options))}")
    return value


def _jrc(t: _Table) -> JrcLineConfig:
    retries = {}
    for key, default in (("retry_1", 10), ("retry_2", 3)):
        retries[key] = t.integer(key, default)
        if retries[key] < 0:
            raise t.fail(key, retries[key], "must be >= 0")
    line = JrcLineConfig(
        port=t.text("port", "/dev/ttyS0"),
        baud=_integer_in(t, "baud", 9600, BAUD_RATES),
        parity=t.choice("parity", ("even", "odd", "none"), "even"),
        data_bits=_integer_in(t, "data_bits", 8, (7, 8)),
        stop_bits=_integer_in(t, "stop_bits", 1, (1, 2)),
        rtscts=t.flag("rtscts", True),
        timer_a_s=t.number("timer_a_s", 3.0, check=_positive, why="must be positive"),
        timer_b_s=t.number("timer_b_s", 20.0, check=_positive, why="must be positive"),
        jwait_slice_s=t.number("jwait_slice_s", 0.5, check=_positive, why="must be positive"),
        **retries,
    )
    t.finish()
    return line


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
        watchdog_s=t.number("watchdog_s", 5.0, check=_positive, why="must be positive"),
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


def _simulation(t: _Table, truth: CellModel) -> SimulationConfig:
    t.table("truth")  # parsed by _truth_tables; marked as known here
    simulation = SimulationConfig(
        seed=t.integer("seed", 0),
        truth=truth,
        scene=_scene(t.table("scene")),
        pixel_noise_px=t.number("pixel_noise_px", 0.0, check=_non_negative, why="must be >= 0"),
        repeatability_m=t.number("repeatability_mm", 0.0, check=_non_negative, why="must be >= 0") / 1000.0,
        repeatability_rad=math.radians(
            t.number("repeatability_deg", 0.0, check=_non_negative, why="must be >= 0")),
        joint_placement_error_m=t.number("joint_placement_error_mm", 0.0, check=_non_negative,
                                         why="must be >= 0") / 1000.0,
        joint_placement_error_rad=math.radians(
            t.number("joint_placement_error_deg", 0.0, check=_non_negative, why="must be >= 0")),
    )
    t.finish()
    return simulation


def parse_cell(data: dict[str, Any], source: str = "<cell>") -> CellConfig:
    """Build a CellConfig from parsed TOML, validating every key.

    The truth is parsed by the same code as the nominal model, from the nominal tables
    with the [simulation.truth.*] overrides laid over them, so an error in an override
    is reported under the nominal key it overrides.
    """
    from vservo.robot_models.loader import ARM_NAMES

    root = _Table(data, "", source)
    robot = root.table("robot")
    arm = robot.choice("arm", ARM_NAMES, "upj")
    home_q = np.deg2rad(robot.vector("home_joints_deg", None, None))
    backend = robot.choice("backend", ROBOT_BACKENDS, "sim")
    robot.finish()

    nominal = _cell_model(root)
    simulation_data = data.get("simulation", {})
    truth_data = simulation_data.get("truth", {}) if isinstance(simulation_data, dict) else {}
    truth = _cell_model(_Table(_truth_tables(data, truth_data, source), "", f"{source} [simulation.truth]"))
    motion = _motion(root.table("motion"))
    simulation = _simulation(root.table("simulation"), truth)
    jrc = _jrc(root.table("jrc"))
    safety = _safety(root.table("safety"))
    root.finish()
    return CellConfig(source, arm, home_q, nominal, motion, simulation, backend, jrc, safety)


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
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None


def load_cell(path: str | Path | None = None) -> CellConfig:
    """Load a cell file; ``None`` loads the default cell shipped in ``static/``."""
    return parse_cell(*read_cell_data(path))
