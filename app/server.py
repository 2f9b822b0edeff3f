"""``vservo serve``: the operator application in the browser, wired to the controller process.

    browser(s) <-- viser (websocket) --> OperatorApp <-- channel --> controller process

The app starts the controller (app/controller_process.py), connects to it with the key,
and serves one page to every browser:

- across the top of every page, the banner: the cell's state at a glance and what to do
  next (app/banner.py); under it, for everyone, the E-STOP and the cell's status line; per
  browser: Reset and the control box (operator token, Take control / Release);
- tabs Assemble, Teach, History, Calibrate (shared displays, per-browser controls that
  only the operator's page enables);
- the live camera panel (image with overlays, feature error and camera twist plots) and
  the 3D cell, the same in every browser.

Threads: viser calls the callbacks in its pool; they only check the role and queue the
command (app/commands.py). The channel's reader writes the session; one display thread
turns the session into page updates at bounded rates (the camera image encoded once for
all browsers). Shared app state (views, job and run lists) is guarded by ``_lock``.
"""

from __future__ import annotations

import contextlib
import io
import logging
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import viser

from vservo.app import live_image
from vservo.app.assemble_panel import AssemblePanel
from vservo.app.banner import Button, Situation, banner_for, live_buttons
from vservo.app.calibrate_panel import CalibratePanel
from vservo.app.client_view import ClientView
from vservo.app.commands import CommandQueue
from vservo.app.context import ServeOptions
from vservo.app.controller_process import ControllerProcess, ControllerStartError
from vservo.app.heap import hold_the_mmap_threshold
from vservo.app.history_panel import HistoryPanel
from vservo.app.roles import RoleRefused, Roles
from vservo.app.scene3d import CellScene
from vservo.app.session import Session, SessionView
from vservo.app.status import status_markdown
from vservo.app.teach_panel import TeachPanel
from vservo.app.web_guard import OriginPolicy, origin_checked_server
from vservo.core.cell.config import CellConfig
from vservo.core.errors import VservoError
from vservo.core.production.protocol import (
    ChannelError,
    Command,
    ControllerClient,
    GetJob,
    JobDetail,
    JobEntry,
    ListJobs,
    ListRuns,
    Reply,
    Reset,
    RunEntry,
)
from vservo.core.terminal.logs import announce

log = logging.getLogger("vservo.app")

IMAGE_PERIOD_S = 1 / 30  # the live image at up to 30 frames per second
TEXT_PERIOD_S = 0.1
SCENE_PERIOD_S = 0.1
PLOT_PERIOD_S = 0.25
WATCH_PERIOD_S = 0.25  # how often the controller process is looked at: a dead one is on the page within 2 s
EXIT_WAIT_S = 2.0  # a controller whose channel ended has that long to exit before it counts as alive
RESTART_RETRY_S = 10.0  # between attempts to start a new controller when one did not come up
BANNER_HEIGHT_PX = 96
# The two docked columns (the control panel left; the E-STOP over the live camera right) leave
# the 3D view between them 216 px of a 1024 px wide window, 472 of 1280 (tests/e2e/test_app_e2e_layout.py);
# the operator drags a column's edge to widen it.
MAIN_WIDTH_PX = 400
LIVE_WIDTH_PX = 400
SAFETY_HEIGHT_PX = 290  # the E-STOP and seven lines of status (a run's); taller when the status needs it
# Viser stacks notifications at the 3D view's top left; in a narrow window they reach into the
# right column: they start under the E-STOP's panel instead, clipped at the window's bottom.
NOTICES_TOP_PX = SAFETY_HEIGHT_PX + 40
ESTOP_Z_INDEX = 1100  # over the banner (1000), notifications (400) and dialogs (Mantine's modal, 200)
# The banner sits fixed over the top of the window; viser's root (#root > div) gives it room.
BANNER_STYLE = f"""<style>
#root > div {{ padding-top: {BANNER_HEIGHT_PX}px; box-sizing: border-box; }}
.vservo-banner {{ position: fixed; top: 0; left: 0; right: 0; height: {BANNER_HEIGHT_PX}px; z-index: 1000;
  color: white; padding: 8px 20px; box-sizing: border-box; overflow: hidden; line-height: 1.3; }}
</style>"""


class OperatorApp:
    def __init__(
        self,
        server: viser.ViserServer,
        client: ControllerClient,
        session: Session,
        roles: Roles,
        config: CellConfig,
        options: ServeOptions,
    ) -> None:
        self.server, self.channel, self.session, self.roles = server, client, session, roles
        self.options = options
        self.commands = CommandQueue(client.call, roles)
        self._lock = threading.Lock()
        self._building = threading.Lock()
        self.views: dict[int, ClientView] = {}
        self.jobs: list[JobEntry] = []
        self.runs: list[RunEntry] = []
        self._job_details: dict[str, JobDetail | None] = {}
        self._stop = threading.Event()

        server.gui.configure_theme(
            control_width="large", show_share_button=False, titlebar_content=None, brand_color=(30, 90, 160)
        )
        server.gui.set_panel_label("vservo cell")
        server.gui.main_panel.dock_left()
        server.gui.main_panel.set_width(MAIN_WIDTH_PX)
        # The banner: the cell's state at a glance, full width over the top of every page
        # (app/banner.py); the panels start below it. Viser has no such element: one HTML
        # element, fixed to the window, with the style that makes room for it.
        self.banner = server.gui.add_html(banner_for(session.state).html(), order=-100)
        server.gui.add_html(BANNER_STYLE, order=-99)
        self.tabs = server.gui.add_tab_group(order=10)
        self.scene = CellScene(server, config)
        self.live = server.gui.add_panel()
        self.live.dock_right()
        self.live.set_width(LIVE_WIDTH_PX)
        # The E-STOP and the status line in a panel of their own, docked at the top of the right
        # column over the live camera: the same place in every tab, never scrolled away, and
        # nothing over the 3D view (the whole arm in sight down to a 1024x640 window).
        self.safety = server.gui.add_panel()
        with self.safety.add_tab("Cell", viser.Icon.ALERT_TRIANGLE):
            estop = server.gui.add_button(
                "E-STOP", color="red", icon=viser.Icon.HAND_STOP, hint="Hold the robot now. Every browser may stop the cell."
            )
            server.gui.add_html(_estop_style(estop._impl.uuid))
            self.status = server.gui.add_markdown("")
        self.safety.dock_above(self.live)
        estop.on_click(lambda event: self.commands.estop(event.client_id, self._estop_reply(event.client_id)))
        self.assemble = AssemblePanel(self, self.tabs.add_tab("Assemble", viser.Icon.PLAYER_PLAY), self.live)
        self.teach = TeachPanel(self, self.tabs.add_tab("Teach", viser.Icon.SCHOOL))
        self.history = HistoryPanel(self, self.tabs.add_tab("History", viser.Icon.HISTORY))
        self.calibrate = CalibratePanel(self, self.tabs.add_tab("Calibrate", viser.Icon.TARGET))
        self.panels = (self.assemble, self.teach, self.history, self.calibrate)

        roles.listeners.append(self._on_operator_change)
        server.on_client_connect(self._on_connect)
        server.on_client_disconnect(self._on_disconnect)
        self._display_thread = threading.Thread(target=self._display, name="app-display", daemon=True)
        self._display_thread.start()
        self.in_background(self.refresh_lists)

    # -- helpers the panels use ----------------------------------------------------------

    def send(
        self,
        view: ClientView,
        what: str,
        command: Command | Callable[[], Command],
        success: str | None = None,
        done: Callable[[Reply], None] | None = None,
    ) -> None:
        """A browser's command: refused at once (in that browser) unless it holds control, or
        when ``command`` (made here from the browser's inputs, if a function) refuses a field."""
        try:
            made = command if isinstance(command, Command) else command()
            self.commands.submit(view.client_id, made, done or view.report(what, success))
        except (RoleRefused, VservoError) as exc:
            view.refused(what, exc)

    def in_background(self, work: Callable[[], None]) -> None:
        def run() -> None:
            try:
                work()
            except ChannelError as exc:
                log.warning("%s", exc)

        threading.Thread(target=run, name="app-refresh", daemon=True).start()

    def refresh_lists(self) -> None:
        """Jobs and runs from the controller; every browser's lists follow."""
        jobs = self.commands.call_now(ListJobs())
        runs = self.commands.call_now(ListRuns(limit=50))
        with self._lock:
            if jobs.ok:
                self.jobs = list(jobs.result)
            if runs.ok:
                self.runs = list(runs.result)
            views = list(self.views.values())
        for panel in self.panels:
            panel.lists_changed(views)
        self.refresh_buttons()

    def job_detail(self, name: str | None) -> JobDetail | None:
        """A job's stored content (poses, settings), fetched once per name and save."""
        if not name:
            return None
        with self._lock:
            if name in self._job_details:
                return self._job_details[name]
        reply = self.commands.call_now(GetJob(name))
        detail = reply.result if reply.ok else None
        with self._lock:
            self._job_details[name] = detail
        return detail

    def forget_job(self, name: str) -> None:
        with self._lock:
            self._job_details.pop(name, None)
        self.assemble.forget_shown_job()

    def job_names(self) -> list[str]:
        with self._lock:
            return [job.name for job in self.jobs if not job.problem]

    def refresh_buttons(self) -> None:
        """Every browser's phase-dependent buttons from what the cell does now (app/banner.py)."""
        state = self.session.state
        with self._lock:
            has_runs = any(run.recording and run.outcome for run in self.runs)
            views = list(self.views.values())
        situation = Situation(
            can_present_part=state.can_present_part,
            commissioning_to_apply=state.commissioning is not None and state.commissioning.to_apply,
            calibrating=self.calibrate.calibrating,
            has_runs=has_runs,
        )
        live = live_buttons(state.phase, situation)
        for view in views:
            view.set_live(live)

    def _estop_reply(self, client_id: int | None) -> Callable[[Reply], None]:
        def done(reply: Reply) -> None:
            with self._lock:
                view = None if client_id is None else self.views.get(client_id)
            if view is None:
                return
            if reply.ok:  # red even when it worked: the robot is held, nothing to celebrate
                view.notify("E-STOP", "robot held", error=True)
            else:
                view.report("E-STOP")(reply)

        return done

    # -- browsers --------------------------------------------------------------------

    def _on_connect(self, client: viser.ClientHandle) -> None:
        view = ClientView(client)
        view.on_detail = self.assemble.show_refusal
        with self._building:  # viser allows one `with tab:` at a time, and browsers connect in parallel
            self._add_control_box(view)
            for panel in self.panels:
                panel.add_client(view)
        with self._lock:
            self.views[client.client_id] = view
        view.set_operator(self.roles.is_operator(client.client_id))
        self.refresh_buttons()

    def _on_disconnect(self, client: viser.ClientHandle) -> None:
        with self._lock:
            self.views.pop(client.client_id, None)
        self.roles.disconnected(client.client_id)
        for panel in self.panels:
            panel.remove_client(client.client_id)

    def _add_control_box(self, view: ClientView) -> None:
        gui = view.client.gui
        reset = view.button(
            Button.RESET,
            gui.add_button("Reset (after e-stop, fault or a finished run)", icon=viser.Icon.REFRESH, order=2, disabled=True),
        )
        reset.on_click(lambda _: self.send(view, "Reset", Reset(), "ready"))
        folder = gui.add_folder("Control", order=3)
        with folder:
            role = gui.add_markdown("")
            token = gui.add_text("Operator token", "", hint="The token printed by `vservo serve` when it started")
            take = gui.add_button("Take control", icon=viser.Icon.LOCK_OPEN)
            release = gui.add_button("Release control", icon=viser.Icon.LOCK, disabled=True)

        def on_take(_: Any) -> None:
            try:
                self.roles.take(view.client_id, token.value, self._client_address(view.client_id))
            except RoleRefused as exc:
                view.refused("Take control", exc)
                return
            token.value = ""  # type: ignore[misc]  # viser's props declare value read-only; its handle sets it

        def on_role(is_operator: bool) -> None:
            role.content = (
                "**Operator**: this browser holds control."
                if is_operator
                else "**Monitor** (read-only): "
                + ("another browser holds control." if self.roles.operator is not None else "no browser holds control.")
            )
            release.disabled, take.disabled = not is_operator, is_operator

        take.on_click(on_take)
        release.on_click(lambda _: None if self.roles.release(view.client_id) else None)
        view.on_role(on_role)

    def _client_address(self, client_id: int) -> str | None:
        """The browser's IP address, which wrong tokens are counted against (a reload must not reset them).

        viser's client handle does not give it; its server keeps each live client's websockets connection.
        """
        connection = self.server._websock_server._live_connections.get(client_id)
        return None if connection is None else str(connection.remote_address[0])

    def _on_operator_change(self, old: int | None, new: int | None) -> None:
        with self._lock:
            views = dict(self.views)
        for client_id, view in views.items():
            try:
                view.set_operator(client_id == new)
            except RuntimeError:  # viser: its elements were removed as it left, before we heard of it
                log.info("browser %d left while control changed hands", client_id)
        if old is not None and old in views and new is not None:
            views[old].notify(
                "Control taken", "Another browser entered the operator token: this one is a monitor now.", error=True
            )
        self._refresh_text(self.session.view())

    # -- the display thread ------------------------------------------------------------------

    def _display(self) -> None:
        done_states = done_frames = runs_ended = 0
        due = {"text": 0.0, "scene": 0.0, "plot": 0.0}
        state_pending = {"text": False, "scene": False, "plot": False}
        last_image = 0.0
        while not self._stop.is_set():
            if not any(state_pending.values()):
                self.session.wait_for_news(done_states, done_frames, 0.5)
            view = self.session.view()
            now = time.monotonic()
            if view.state_number != done_states:
                done_states = view.state_number
                state_pending = dict.fromkeys(state_pending, True)
            try:
                if view.frame is not None and view.frame.number != done_frames and now - last_image >= IMAGE_PERIOD_S:
                    done_frames, last_image = view.frame.number, now
                    self.assemble.show_frame(view.frame)
                    self.teach.refresh_seen(view)
                for name, period, update in (
                    ("text", TEXT_PERIOD_S, self._refresh_text),
                    ("scene", SCENE_PERIOD_S, self._refresh_scene),
                    ("plot", PLOT_PERIOD_S, self.assemble.refresh_plots),
                ):
                    if state_pending[name] and now >= due[name]:
                        update(view)
                        state_pending[name], due[name] = False, now + period
                if view.runs_ended != runs_ended:
                    runs_ended = view.runs_ended
                    self.in_background(self.refresh_lists)
            except Exception:  # one bad update must not freeze every browser's page
                log.exception("display update failed")
            time.sleep(max(0.0, IMAGE_PERIOD_S - (time.monotonic() - now)))

    def _refresh_text(self, view: SessionView) -> None:
        banner = banner_for(view.state, view.controller_gone).html()
        if self.banner.content != banner:
            self.banner.content = banner
        self.status.content = status_markdown(view.state, self.roles.operator is not None, view.controller_gone)
        self.refresh_buttons()
        for panel in self.panels:
            panel.refresh(view)

    def _refresh_scene(self, view: SessionView) -> None:
        overlay = live_image.Overlay.from_meta(view.frame.meta) if view.frame is not None else None
        self.scene.update(view.state, overlay, view.trace.path_m)
        self.teach.follow_flange(view.state.bMe)

    def reconnect(self, channel: ControllerClient) -> None:
        """A new controller in place of one that died: commands go to it, the pages show its state
        and the runs it found unfinished (marked interrupted)."""
        self.channel = channel
        self.commands.reconnect(channel.call)
        self.session.on_controller_back(channel.state)
        self.in_background(self.refresh_lists)

    def close(self) -> None:
        self._stop.set()
        self._display_thread.join(5.0)
        self.calibrate.close()
        self.commands.close()


def _estop_style(uuid: str) -> str:
    """The E-STOP's style: large (viser has no button size; it sets its icons half their width
    right of their box, which at this size runs the hand into the label's "E"); its panel as tall
    as its content, at least SAFETY_HEIGHT_PX (viser shares a docked column's height half and
    half; the E-STOP must never scroll out of its panel), the live camera under it taking the
    rest; and nothing over it: notifications start under its panel, which stays on top of any
    other element or dialog (its column is made no stacking context of its own, which would
    hold the panel under a dialog's overlay)."""
    button = f"button[id='{uuid}']"
    return (
        f"<style>{button} {{height: 84px !important; font-size: 1.8em; font-weight: 800; letter-spacing: 0.12em}} "
        f"{button} svg {{left: 0 !important}} "
        f"[data-dock-scroll] > div:has({button}) {{flex: 0 0 auto !important; min-height: {SAFETY_HEIGHT_PX}px !important}} "
        f"[data-dock-leaf]:has({button}) div {{flex-basis: auto !important}} "
        f"[data-dock-region]:has({button}) {{z-index: auto !important}} "
        f"[data-dock-scroll]:has({button}) > div:has([data-dock-leaf]):not(:has({button})) {{flex-grow: 1 !important}} "
        f".mantine-Paper-root:has({button}) {{position: relative; z-index: {ESTOP_Z_INDEX} !important}} "
        f".mantine-Notifications-root {{top: {NOTICES_TOP_PX}px !important; bottom: 0; overflow: hidden}}</style>"
    )


@dataclass
class RunningApp:
    """The app serving, with the controller process it started."""

    app: OperatorApp
    server: viser.ViserServer
    channel: ControllerClient
    controller: ControllerProcess
    url: str
    options: ServeOptions
    lost: threading.Event  # set by the channel's reader as the channel ends

    def watch_controller(self, stop: threading.Event) -> None:
        """Until ``stop``: a controller process that stopped (its channel ended) is said on every
        page at once (nothing holds the robot for vservo meanwhile), and a new one started and connected."""
        while not stop.is_set():
            if not self.lost.wait(WATCH_PERIOD_S) and self.controller.alive:
                continue
            if stop.is_set():
                break
            self.app.session.on_controller_gone("the channel to the controller process closed")  # the pages at once
            code = self.controller.exit_code(EXIT_WAIT_S)
            if stop.is_set():  # Ctrl-C at the terminal stops the controller and this app together
                break
            why = (
                "the channel to the controller process closed (the process still ran: it is stopped)"
                if code is None
                else f"the controller process stopped ({_exit_words(code)})"
            )
            log.error("%s: starting a new one", why)
            self.app.session.on_controller_gone(why)
            while not stop.is_set() and (failed := self._restart_controller()) is not None:
                self.app.session.on_controller_gone(f"{why}; a new one did not start: {failed}")
                stop.wait(RESTART_RETRY_S)

    def _restart_controller(self) -> str | None:
        """A new controller process on the same cell and data (it marks the run the old one left
        interrupted), the app reconnected to it; why not, if it did not come up."""
        self.controller.stop()  # reaps the dead one (a live one, whose channel ended, holds the robot and exits)
        # The new channel's own event: the old channel's reader, late under load, or its close
        # below would otherwise say the new channel ended, and a sound controller be stopped.
        lost = threading.Event()
        try:
            controller = _start_controller(self.options)
        except ControllerStartError as exc:
            return str(exc)
        try:
            channel = _connect(controller, self.app.session, lost)
        except ChannelError as exc:
            controller.stop()
            return str(exc)
        old, self.controller, self.channel, self.lost = self.channel, controller, channel, lost
        self.app.reconnect(channel)
        old.close()
        log.warning("a new controller process (PID %d) is connected", controller.process.pid)
        return None

    def close(self) -> int | None:
        """Stop serving and stop the controller (SIGTERM: it holds the robot and exits); its exit code."""
        self.app.close()
        code = self.controller.stop()
        self.channel.close()
        with contextlib.redirect_stdout(io.StringIO()):  # viser says "Server stopped" on standard output
            self.server.stop()
        return code


def start_app(options: ServeOptions, config: CellConfig) -> RunningApp:
    """Start the controller process, connect to it and serve the page (returns once serving)."""
    roles = Roles(options.token)
    controller = _start_controller(options)
    try:
        session, lost = Session(), threading.Event()
        channel = _connect(controller, session, lost)
        policy = OriginPolicy.allowing(options.allowed_origins)
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner whatever verbose says; ours is below
            server = origin_checked_server(options.host, options.port, policy)
        port = server.get_port()
        if port != options.port:
            log.warning("port %d was taken: serving on %d", options.port, port)
        app = OperatorApp(server, channel, session, roles, config, options)
    except BaseException:
        controller.stop()  # never leave the controller running without its app
        raise
    return RunningApp(app, server, channel, controller, f"http://{options.host}:{port}", options, lost)


def _start_controller(options: ServeOptions) -> ControllerProcess:
    return ControllerProcess.start(
        backend=options.backend,
        data=options.data,
        seed=options.seed,
        cycle_period_s=options.cycle_period_s,
        time_scale=options.time_scale,
        cell=options.cell,
        log_options=options.log_options,
    )


def _connect(controller: ControllerProcess, session: Session, lost: threading.Event) -> ControllerClient:
    """The channel to ``controller``, its states and frames into ``session``; ``lost`` set as it ends."""
    channel = ControllerClient(
        controller.address, controller.key, on_state=session.on_state, on_frame=session.on_frame, on_closed=lost.set
    )
    session.on_state(channel.state)  # the welcome's state (ignored if a newer one came first)
    return channel


def _exit_words(code: int | None) -> str:
    return f"killed by signal {-code}" if code is not None and code < 0 else f"exit code {code}"


def serve(options: ServeOptions, config: CellConfig, announce: Callable[[str], None] = print) -> int:
    """Run the app until SIGTERM / SIGINT: start the controller, serve the page, stop the controller."""
    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda *_: stop.set())
    threading.excepthook = _log_thread_exception
    hold_the_mmap_threshold()  # before the first browser: the heap keeps nothing of those that left
    running = start_app(options, config)
    try:
        token = options.token if options.show_token else "(the one given)"
        announce(f"vservo serve: {running.url}  operator token: {token}  (backend {options.backend}, data {options.data})")
        running.watch_controller(stop)
    finally:
        code = running.close()
    return 0 if code in (0, None) else 1


def _log_thread_exception(args: threading.ExceptHookArgs) -> None:
    log.error(
        "unhandled exception in thread %s",
        args.thread.name if args.thread else "?",
        exc_info=args.exc_value,
    )
    announce(f"vservo serve: unhandled exception in thread {args.thread.name if args.thread else '?'}: {args.exc_value!r}")
