"""The virtual cell: the simulated cell as its own process, behind a real cell's interfaces.

The controller reaches it only as it reaches hardware, through the cell file it writes:

- the robot: the JRC emulator on a pseudo-terminal (``[jrc] port``) or, as a DX100 or
  later controller's Ethernet server, on a loopback TCP port (``[jrc] transport =
  "ethernet"``, ``host``, ``port``), the only thing that moves the plant; the vacuum cup
  on the emulator's I/O (``[vacuum] device = "jrc_io"``);
- the camera: an MJPEG stream over HTTP that OpenCV opens by URL
  (``[camera.source] device``), exposed on a steady frame clock and sent a camera's
  latency later;
- the fixture (``[fixture] url``): a JSON port that presents a new part (near where the
  job was taught, or at a given place), lays the calibration checkerboard on the table or
  takes it away, and gauges where a released part truly ended: what a test cell has and
  a production cell does without;
- the I/O panel a PLC is wired to, for a PLC on the JRC's I/O (``[line.plc] transport =
  "jrc_io"``): the fixture's /io switches the PLC's signals on the JRC's inputs and reads
  what the JRC's ladder sends back (a test's PLC program drives it).

The plant plays the TRUE cell: the ``--cell`` file's [simulation] with the ``--truth``
file's [simulation.truth.*] laid over it. The cell file written for the controller holds
the nominal sections only, so nothing of the truth reaches it.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import numpy as np

from vservo.core.cell.cell_file import dumps_cell
from vservo.core.cell.config import (
    ETHERNET_ONLY_KEYS,
    SERIAL_ONLY_KEYS,
    CellConfig,
    ConfigError,
    HostTransport,
    VacuumDeviceConfig,
    parse_cell,
)
from vservo.core.perception.recording import write_atomic
from vservo.core.sim.camera_stream import CameraStream
from vservo.core.sim.jrc_emulator import JrcEmulator
from vservo.core.sim.part_feeder import place_part, present_part
from vservo.core.sim.plant import CellStateError, SimulatedCell
from vservo.core.sim.render import SceneRenderer
from vservo.core.sim.render_settings import RenderSettings

log = logging.getLogger("vservo.virtual_cell")

# The cup's wiring when the --cell file does not put it on the JRC's I/O: the first
# network input for suction, the first external input for the pressure switch.
DEFAULT_VACUUM_IO = VacuumDeviceConfig("jrc_io", suction_output=27010, grip_input=20)


@dataclass(frozen=True)
class VirtualCellSettings:
    """time_scale: the emulated JRC and the plant run this many times faster than a real
    cell (the controller's sampling period in the written cell file shrinks as much).
    fps, exposure_latency_s: the camera stream's (its JPEG quality stays the stream's default, 100:
    at 95 the laser stage stalled on the demo job, docs/vision.md). latency_margin_s: what the
    written cell file adds to the camera's latency for the network and the decoder, so
    that its ``exposure_latency_s`` is an upper bound. robot_link: what carries the host
    commands to the emulated JRC: a pseudo-terminal (BSC), or a loopback TCP port (the
    Ethernet server of later controllers)."""

    time_scale: float = 40.0
    fps: float = 30.0
    exposure_latency_s: float = 0.05
    latency_margin_s: float = 0.05
    release_poll_s: float = 0.01
    robot_link: HostTransport = HostTransport.SERIAL


@dataclass(frozen=True)
class Addresses:
    """Where the virtual cell's devices appear; by default wherever the system puts them.

    Fixed ones let a virtual cell restarted after a crash come back where the controller
    looks for it, as a real cell's devices do (a serial adapter's /dev/serial/by-id name,
    a camera's address): jrc_link is a symbolic link to the JRC's pseudo-terminal, put in
    place at every start; jrc_tcp_port (the JRC's Ethernet server, when it has one),
    camera_port and fixture_port are TCP ports (0: any free one).
    """

    jrc_link: Path | None = None
    camera_port: int = 0
    fixture_port: int = 0
    jrc_tcp_port: int = 0


@dataclass(frozen=True)
class Released:
    """A part the cup let go, gauged: inside the pocket, and its centre's offset from the pocket's."""

    inside: bool
    placement_error_mm: float

    def as_dict(self) -> dict[str, Any]:
        return {"event": "released", "inside": self.inside, "placement_error_mm": round(self.placement_error_mm, 4)}


def jrc_table(cell_jrc: dict[str, Any], link: dict[str, Any], time_scale: float) -> dict[str, Any]:
    """The controller's [jrc]: the --cell file's settings with the virtual JRC's link keys
    (``link``) and time scale, less the keys only the other link has."""
    foreign = SERIAL_ONLY_KEYS if link.get("transport") == HostTransport.ETHERNET else ETHERNET_ONLY_KEYS
    kept = {k: v for k, v in cell_jrc.items() if k not in (*foreign, "transport", "port")}
    return {**kept, **link, "time_scale": time_scale}


def controller_tables(
    cell_tables: dict[str, Any],
    *,
    jrc_link: dict[str, Any],
    camera_url: str,
    fixture_url: str,
    vacuum: VacuumDeviceConfig,
    settings: VirtualCellSettings,
) -> dict[str, Any]:
    """The cell file the controller gets: the nominal cell, wired to this virtual cell's devices."""
    tables = {k: copy.deepcopy(v) for k, v in cell_tables.items() if k != "simulation"}
    tables.setdefault("robot", {})["backend"] = "jrc"
    tables["jrc"] = jrc_table(tables.get("jrc", {}), jrc_link, settings.time_scale)
    camera = tables.setdefault("camera", {})
    camera["source"] = {
        "kind": "capture",
        "device": camera_url,
        "exposure_latency_s": round(settings.exposure_latency_s + settings.latency_margin_s, 4),
        "buffer_frames": 0,
        "reconnect_attempts": 3,
        "reconnect_delay_s": 0.5,
    }
    tables.setdefault("vacuum", {}).update(device="jrc_io", suction_output=vacuum.suction_output, grip_input=vacuum.grip_input)
    motion = tables.setdefault("motion", {})
    motion["sampling_period_s"] = float(motion.get("sampling_period_s", 2.0)) / settings.time_scale
    tables["fixture"] = {"url": fixture_url}
    return tables


class VirtualCell:
    """The plant, its JRC, its camera stream and its fixture; ``start`` brings them up."""

    def __init__(
        self,
        tables: dict[str, Any],
        source: str,
        seed: int | None = None,
        settings: VirtualCellSettings = VirtualCellSettings(),
        on_released: Callable[[Released], None] = lambda released: None,
        board_laid: bool = False,
        addresses: Addresses = Addresses(),
    ) -> None:
        self.tables, self.source, self.settings, self.on_released = tables, source, settings, on_released
        self.addresses = addresses
        # Its robot is a JRC whatever the file's [robot] backend says (the controller's file says "jrc").
        self.config: CellConfig = parse_cell({**tables, "robot": {**tables.get("robot", {}), "backend": "jrc"}}, source)
        self.cell = SimulatedCell(self.config, seed)
        if board_laid:
            self.cell.lay_board(True)
        self.taught_bMo = self.config.plant().scene.cube.bMo
        self.vacuum = self.config.vacuum_device if self.config.vacuum_device.device == "jrc_io" else DEFAULT_VACUUM_IO
        self.emulator = JrcEmulator(
            self.cell, self.config.jrc, time_scale=settings.time_scale, vacuum=self.vacuum, plc=self.config.plc
        )
        self.renderer = SceneRenderer(self.cell.truth.model.camera, RenderSettings())
        self.camera_rng = np.random.default_rng(self.cell.rng.integers(2**31))
        self.camera = CameraStream(
            self._render, fps=settings.fps, exposure_latency_s=settings.exposure_latency_s, port=addresses.camera_port
        )
        self.fixture = _FixtureServer(self, port=addresses.fixture_port)
        self.released: list[Released] = []
        self.jrc_port: str | None = None  # where the emulator serves, once started: its pseudo-terminal, or host:port
        self._jrc_keys: dict[str, Any] = {}  # the controller's [jrc] keys for the link, once started
        self._stop = threading.Event()
        self._watch: threading.Thread | None = None

    # -- running -----------------------------------------------------------------------

    def start(self) -> None:
        if self.settings.robot_link is HostTransport.ETHERNET:
            host, port = self.emulator.start_on_tcp(port=self.addresses.jrc_tcp_port)
            self.jrc_port = f"{host}:{port}"
            self._jrc_keys = {"transport": str(HostTransport.ETHERNET), "host": host, "port": port}
        else:
            self._start_on_pty()
        self.camera.start()
        self.fixture.start()
        self._watch = threading.Thread(target=self._watch_releases, name="release-gauge", daemon=True)
        self._watch.start()

    def _start_on_pty(self) -> None:
        self.jrc_port = self.emulator.start_on_pty()
        if self.addresses.jrc_link is not None:
            # A new link beside the old one, then renamed over it: the name is never missing
            # or left pointing at a dead pseudo-terminal by this start.
            fresh = self.addresses.jrc_link.with_name(self.addresses.jrc_link.name + ".new")
            fresh.unlink(missing_ok=True)
            fresh.symlink_to(self.jrc_port)
            fresh.replace(self.addresses.jrc_link)
            self.jrc_port = str(self.addresses.jrc_link)
        # Linux drops a pseudo-terminal's parity bit and then refuses it on the next opening,
        # so the virtual JRC's line runs without parity (pendant RS032 allows none).
        self._jrc_keys = {"port": self.jrc_port, "parity": "none"}

    def close(self) -> None:
        """Stop everything; safe to call twice."""
        self._stop.set()
        if self._watch is not None:
            self._watch.join()
            self._watch = None
        self.fixture.close()
        self.camera.close()
        self.emulator.stop()

    def __enter__(self) -> VirtualCell:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def write_cell_file(self, path: str | Path) -> Path:
        """The controller's cell file for this running virtual cell."""
        if self.jrc_port is None:
            raise RuntimeError("the virtual cell is not started: its devices have no addresses yet")
        path = Path(path)
        tables = controller_tables(
            self.tables,
            jrc_link=self._jrc_keys,
            camera_url=self.camera.url,
            fixture_url=self.fixture.url,
            vacuum=self.vacuum,
            settings=self.settings,
        )
        header = (
            f"The virtual cell's devices (vservo virtual-cell, from {self.source}), written "
            f"{time.strftime('%Y-%m-%d %H:%M:%S')}.\nValid while that process runs: its JRC port, camera "
            "stream and fixture go with it."
        )
        write_atomic(path, dumps_cell(tables, header).encode("utf-8"))
        return path

    # -- the plant's sensors and fixture ---------------------------------------------------

    def _render(self) -> np.ndarray:
        """The TRUE view now: the plant brought up to this moment, rendered outside the lock."""
        with self.emulator.lock:
            self.emulator.advance()
            bMc, spot_b = self.cell.ground_truth_view()
            scene = self.cell.state.scene
        return self.renderer.render(scene, bMc, spot_b, self.camera_rng)

    def _check_still(self, action: str) -> None:
        """Refuse ``action`` while the arm moves (call with the emulator's lock held)."""
        self.emulator.advance()
        if self.emulator.motion is not None:
            raise CellStateError(f"the arm is moving: {action} only while it stands still")

    def present_part(self, seed: int | None) -> dict[str, float]:
        rng = np.random.default_rng(seed) if seed is not None else self.cell.rng
        with self.emulator.lock:
            self._check_still("a part is presented")
            bMo = present_part(self.cell, self.taught_bMo, rng)
        return _planar_pose(bMo)

    def place_part(self, x_mm: float, y_mm: float, yaw_deg: float) -> dict[str, float]:
        """The part put down with its frame O at (x_mm, y_mm) on the table, turned yaw_deg."""
        with self.emulator.lock:
            self._check_still("a part is put down")
            bMo = place_part(self.cell, x_mm / 1000.0, y_mm / 1000.0, np.radians(yaw_deg))
        return _planar_pose(bMo)

    def lay_board(self, laid: bool) -> dict[str, bool]:
        """Lay the checkerboard (the table cleared of the parts) or take it away."""
        with self.emulator.lock:
            self._check_still("the board is laid or taken away")
            self.cell.lay_board(laid)
        return self.board_state()

    def board_state(self) -> dict[str, bool]:
        with self.emulator.lock:
            return {"laid": self.cell.board_laid}

    def part_pose(self) -> dict[str, float]:
        with self.emulator.lock:
            return _planar_pose(self.cell.state.scene.cube.bMo)

    def _watch_releases(self) -> None:
        """Gauge each part the cup lets go, as it comes to rest."""
        was_holding = False
        while not self._stop.wait(self.settings.release_poll_s):
            with self.emulator.lock:
                holding = self.cell.holding_part
                placement = None if holding or not was_holding else self.cell.ground_truth_placement()
            was_holding = holding
            if placement is not None:
                released = Released(bool(placement.inside), 1000.0 * placement.error_m)
                self.released.append(released)
                self.on_released(released)


def _planar_pose(bMo: np.ndarray) -> dict[str, float]:
    """A part's pose on the table: its frame's origin in mm and its turn about the vertical."""
    return {
        "x_mm": round(1000.0 * float(bMo[0, 3]), 4),
        "y_mm": round(1000.0 * float(bMo[1, 3]), 4),
        "z_mm": round(1000.0 * float(bMo[2, 3]), 4),
        "yaw_deg": round(float(np.degrees(np.arctan2(bMo[1, 0], bMo[0, 0]))), 4),
    }


class _FixtureServer:
    """The fixture's JSON port (ENDPOINTS). POST /part presents a part near the taught
    place ({"seed": n} optional) or puts it at a given place ({"x_mm", "y_mm", "yaw_deg"}:
    its frame O, a top-face corner, on the table); GET /part says where the part truly
    is; POST /board ({"laid": true|false}) lays the checkerboard or takes it away, GET
    /board says which; GET /released lists the gauged releases. The JRC's I/O panel, for
    a PLC on the JRC's I/O ([line.plc] transport = "jrc_io"): POST /io ({"inputs":
    {"<address>": true|false}}) switches the PLC's signals on the JRC's inputs, GET /io
    reads them and the outputs the JRC's ladder sends the PLC."""

    def __init__(self, virtual: VirtualCell, host: str = "127.0.0.1", port: int = 0) -> None:
        self.server = ThreadingHTTPServer((host, port), _handler_for(virtual))
        self.server.daemon_threads = True
        self.url = f"http://{host}:{self.server.server_address[1]}"
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self.server.serve_forever, name="fixture", daemon=True)
        self._thread.start()

    def close(self) -> None:
        if self._thread is not None:
            self.server.shutdown()
            self._thread.join()
            self._thread = None
        self.server.server_close()


ENDPOINTS = ("POST /part", "GET /part", "POST /board", "GET /board", "GET /io", "POST /io", "GET /released")
_PART_BODY = 'the body is empty, {"seed": <integer>}, or {"x_mm": <number>, "y_mm": <number>, "yaw_deg": <number>}'
_BOARD_BODY = 'the body is {"laid": true} or {"laid": false}'
_IO_BODY = 'the body is {"inputs": {"<byte.bit address>": true|false, ...}}, at the addresses of [line.plc.inputs]'


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _post_part(virtual: VirtualCell, body: dict[str, Any]) -> dict[str, Any]:
    if set(body) <= {"seed"}:
        seed = body.get("seed")
        if not (seed is None or (isinstance(seed, int) and not isinstance(seed, bool))):
            raise ValueError(f"seed = {seed!r} is not an integer: {_PART_BODY}")
        return {"part": virtual.present_part(seed)}
    place = {"x_mm", "y_mm", "yaw_deg"}
    if not set(body) <= place or not {"x_mm", "y_mm"} <= set(body):
        raise ValueError(f"keys {sorted(body)}: {_PART_BODY}")
    body = {"yaw_deg": 0.0, **body}
    for key in sorted(place):
        if not _is_number(body[key]):
            raise ValueError(f"{key} = {body[key]!r} is not a finite number: {_PART_BODY}")
    return {"part": virtual.place_part(float(body["x_mm"]), float(body["y_mm"]), float(body["yaw_deg"]))}


def _post_board(virtual: VirtualCell, body: dict[str, Any]) -> dict[str, Any]:
    if set(body) != {"laid"} or not isinstance(body["laid"], bool):
        raise ValueError(f"{json.dumps(body)}: {_BOARD_BODY}")
    return {"board": virtual.lay_board(body["laid"])}


def _io_panel(virtual: VirtualCell) -> dict[str, Any]:
    panel = virtual.emulator.io_panel()
    return {
        "inputs": {str(address): on for address, on in panel.inputs.items()},
        "outputs": {str(address): on for address, on in panel.outputs.items()},
    }


def _post_io(virtual: VirtualCell, body: dict[str, Any]) -> dict[str, Any]:
    signals = body.get("inputs")
    if set(body) != {"inputs"} or not isinstance(signals, dict) or not all(isinstance(on, bool) for on in signals.values()):
        raise ValueError(f"{json.dumps(body)}: {_IO_BODY}")
    try:
        wanted = {int(address): on for address, on in signals.items()}
    except ValueError:
        raise ValueError(f"{json.dumps(body)}: {_IO_BODY}") from None
    virtual.emulator.set_inputs(wanted)
    return _io_panel(virtual)


_POSTS: dict[str, Callable[[VirtualCell, dict[str, Any]], dict[str, Any]]] = {
    "/part": _post_part,
    "/board": _post_board,
    "/io": _post_io,
}


def _handler_for(virtual: VirtualCell) -> type[BaseHTTPRequestHandler]:
    class FixtureHandler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 (http.server's name)
            if self.path == "/part":
                self._reply(200, {"part": virtual.part_pose()})
            elif self.path == "/board":
                self._reply(200, {"board": virtual.board_state()})
            elif self.path == "/io":
                self._reply(200, _io_panel(virtual))
            elif self.path == "/released":
                self._reply(200, {"released": [r.as_dict() for r in virtual.released]})
            elif self.path == "/":
                self._reply(200, {"fixture": "vservo virtual cell", "endpoints": list(ENDPOINTS)})
            else:
                self._reply(404, {"error": f"no such endpoint: GET {self.path}"})

        def do_POST(self) -> None:  # noqa: N802
            post = _POSTS.get(self.path)
            if post is None:
                self._reply(404, {"error": f"no such endpoint: POST {self.path}"})
                return
            try:
                length = int(self.headers.get("Content-Length") or 0)
                if length > 4096:
                    raise ValueError(f"a body of {length} bytes is too long for the fixture")
                body = json.loads(self.rfile.read(length) or b"{}")
                if not isinstance(body, dict):
                    raise ValueError(f"the body must be a JSON object, got {json.dumps(body)}")
                self._reply(200, post(virtual, body))
            except (RuntimeError, ConfigError) as exc:  # the cell's state (CellStateError), or a cell without a board
                self._reply(409, {"error": str(exc)})
            except ValueError as exc:  # json.JSONDecodeError is one
                self._reply(400, {"error": str(exc)})

        def _reply(self, status: int, body: dict) -> None:
            data = json.dumps(body).encode()
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)

        def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 (http.server's signature)
            log.debug("fixture: " + format, *args)

    return FixtureHandler
