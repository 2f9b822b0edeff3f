"""What the server shares with its tabs: the serve options and the app's services.

Each tab (assemble, teach, history, calibrate) gets the running app as an AppContext and
uses nothing else of it, so the panels never import the server that builds them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import viser

from vservo.app.client_view import ClientView
from vservo.app.roles import Roles
from vservo.app.scene3d import CellScene
from vservo.app.session import Session
from vservo.core.production.protocol import Command, JobDetail, Reply, RunEntry


@dataclass(frozen=True)
class ServeOptions:
    backend: str = "sim"
    host: str = "127.0.0.1"
    port: int = 8080
    data: Path = Path(".")
    seed: int | None = None
    token: str = ""
    cycle_period_s: float = 0.05
    # The simulated cell's pace: S times the real cell's; None (the tests', the benches'): as fast
    # as it computes. `vservo serve` gives its --time-scale, 1 by default.
    time_scale: float | None = None
    cell: str | None = None
    show_token: bool = True  # print it when serving starts: only a generated one, which nobody else knows yet
    allowed_origins: tuple[str, ...] = ()  # web pages besides the app's own that may open its WebSocket
    log_options: tuple[str, ...] = ()  # --log-level and --log-format, handed on to the controller process


class AppContext(Protocol):
    server: viser.ViserServer
    session: Session
    roles: Roles
    options: ServeOptions
    scene: CellScene
    runs: list[RunEntry]

    def send(
        self,
        view: ClientView,
        what: str,
        command: Command | Callable[[], Command],
        success: str | None = None,
        done: Callable[[Reply], None] | None = None,
    ) -> None:
        """A browser's command (or how to make it from its inputs), refused in that browser
        unless it holds control or when its fields are out of range."""
        ...

    def in_background(self, work: Callable[[], None]) -> None: ...

    def refresh_lists(self) -> None:
        """Fetch jobs and runs from the controller; every tab's lists follow."""
        ...

    def refresh_buttons(self) -> None:
        """Enable every browser's phase-dependent buttons from what the cell does now."""
        ...

    def job_detail(self, name: str | None) -> JobDetail | None: ...

    def forget_job(self, name: str) -> None:
        """The job ``name`` was saved anew: its cached detail and the shown job are stale."""
        ...

    def job_names(self) -> list[str]: ...
