"""A test cell's fixture, reached over its JSON port: it presents new parts and lays the board.

A production cell has none: parts arrive by hand or on a conveyor, and an integrator lays
the calibration checkerboard. A test cell (the virtual cell of ``vservo virtual-cell``)
has a fixture that puts a new part on the table on request (near where the job was
taught, or at a given place), lays the checkerboard or takes it away, gauges where a
released part ended, and keeps the cell clock of its emulated controller; the controller
uses all but the gauge, and measures placement itself, by vision. The cell file names
the fixture with ``[fixture] url``; its endpoints are in docs/connecting-your-cell.md.
"""

from __future__ import annotations

import json
import logging
import urllib.error
import urllib.request

import numpy as np

from vservo.core.errors import VservoError

log = logging.getLogger("vservo.fixture")


class FixtureError(VservoError, RuntimeError):
    """The fixture did not do what was asked; the message says what and why."""


class FixtureClient:
    def __init__(self, url: str, timeout_s: float = 5.0) -> None:
        self.url, self.timeout_s = url.rstrip("/"), timeout_s

    def present_part(self, rng: np.random.Generator) -> dict:
        """A new part on the table; ``rng`` draws the seed of where it lands, so a run's
        ``--seed`` decides the part's arrival here as on the simulated cell."""
        return self._request("POST", "/part", {"seed": int(rng.integers(2**31))})

    def place_part(self, x_m: float, y_m: float, yaw_rad: float) -> dict:
        """The part put down with its frame O (a top-face corner) at (x_m, y_m) in the base
        frame, turned yaw_rad about the vertical; the fixture refuses a place off its table
        or on the metal part."""
        return self._request("POST", "/part", {"x_mm": 1000.0 * x_m, "y_mm": 1000.0 * y_m, "yaw_deg": float(np.degrees(yaw_rad))})

    def lay_board(self, laid: bool) -> dict:
        """Lay the calibration checkerboard on the table (the parts cleared off it), or take it away."""
        return self._request("POST", "/board", {"laid": bool(laid)})

    def cell_time_s(self) -> float:
        """The test cell's clock: what its emulated controller would take on a real cell
        (each motion's duration, each exchange's bytes at the line's rate); NaN, said in the
        log, when the fixture cannot tell (a run's cell time is then unknown, the run goes on)."""
        try:
            seconds = self._request("GET", "/clock").get("cell_time_s")
        except FixtureError as exc:
            log.warning("no cell time: %s", exc)
            return float("nan")
        if isinstance(seconds, bool) or not isinstance(seconds, (int, float)):
            log.warning("no cell time: fixture %s: GET /clock answered %r", self.url, seconds)
            return float("nan")
        return float(seconds)

    def _request(self, method: str, path: str, body: dict | None = None) -> dict:
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.url + path, data=data, method=method, headers={"Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(request, timeout=self.timeout_s) as response:
                return json.loads(response.read() or b"{}")
        except urllib.error.HTTPError as exc:
            raise FixtureError(
                f"fixture {self.url}: {method} {path} refused ({exc.code}): {exc.read().decode(errors='replace').strip()}"
            ) from None
        except (urllib.error.URLError, OSError, json.JSONDecodeError) as exc:
            raise FixtureError(f"fixture {self.url}: {method} {path} failed: {exc}") from None
