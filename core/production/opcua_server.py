"""The cell's OPC UA server for the plant's MES or SCADA ([line.opcua] in the cell file).

A thin part of the controller process, never a second path to the robot: it reads what the
controller publishes (the state every client of the controller's channel gets) and carries
out its methods with the channel's own commands (core/production/protocol/commands.py):
``Start`` is the page's Start command, checked by the same dataclass and carried out by
the same controller method, behind the same guards (phase, e-stop, the robot's alarm, the
safety layer on every move, one command at a time under the command lock). ``Hold`` is the
page's E-STOP (the robot held now, every move refused until Reset), ``Reset`` the page's.

The address space, under Objects (namespace ``urn:vservo:cell``, string node ids as below)::

    Cell                      Phase, Detail, EStopped, Fault, Ready, Busy, Backend, Robot,
                              Jobs (the names of the jobs a Start may name), LastRefusal
    Cell.CurrentRun           Active, RunId, Job, PartId, Stage, Iteration, ErrorPx
    Cell.LastRun              RunId, Job, PartId, Outcome, Reason, PlacementErrorMm,
                              FinalErrorPx, CycleTimeS, CellTimeS, Iterations
    Cell.Start(JobName, PartId) -> RunId      Cell.Hold()      Cell.Reset()

A number not measured is NaN (a placement without a check view), a run id none is -1.
A method the controller refuses answers BadInvalidState (BadInvalidArgument for a field out
of range), its one-line reason in ``Cell.LastRefusal``. Every variable is read-only. Users
log in with the name and password of [line.opcua.users.NAME]; an anonymous client may browse,
read and subscribe (``anonymous = "read-only"``) or is refused (``"off"``), and a write or a
method call of an anonymous session is refused (BadUserAccessDenied) before it reaches the
controller.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from asyncua import Server, ua
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, User, UserRole
from asyncua.server.user_managers import UserManager

from vservo.core.cell.line import AnonymousAccess, OpcUaConfig, endpoint_url
from vservo.core.errors import VservoError
from vservo.core.production.cell_controller import CellController
from vservo.core.production.protocol import CommandRefused, ControllerState, ListJobs, Phase, Reset, Start
from vservo.core.production.protocol.state import MOVING

log = logging.getLogger("vservo.opcua")

NAMESPACE = "urn:vservo:cell"
PUBLISH_PERIOD_S = 0.1  # the variables follow the controller's state at most this often
START_TIMEOUT_S = 60.0
NO_RUN = -1
MAX_WRONG_PASSWORDS = 5  # in a row, for one user name (OpcUaUsers)
LOCKOUT_S = 60.0
_READY = frozenset({Phase.IDLE, Phase.DONE})  # where a Start is taken (a fault needs Reset first)


def _node(identifier: str | int, namespace: int = 0) -> ua.NodeId:
    """A node id of a string or numeric identifier (asyncua types the two apart)."""
    value = ua.String(identifier) if isinstance(identifier, str) else ua.Int32(identifier)
    return ua.NodeId(value, ua.Int16(namespace))


_WRITES = frozenset(
    _node(request)
    for request in (ua.ObjectIds.WriteRequest_Encoding_DefaultBinary, ua.ObjectIds.CallRequest_Encoding_DefaultBinary)
)
_REQUESTS = frozenset(_node(request) for request in USER_TYPES)


class OpcUaError(VservoError, RuntimeError):
    """The OPC UA server could not start; the message says why."""


class _Permissions(PermissionRuleset):
    """What a session may ask: a user, what asyncua lets a user do (never change the
    address space); an anonymous one the same but a write or a method call."""

    def check_validity(self, user: User, action_type_id: ua.NodeId, body: Any) -> bool:
        if action_type_id not in _REQUESTS:
            return False
        return user.role is not UserRole.Anonymous or action_type_id not in _WRITES


class OpcUaUsers(UserManager):
    """The cell file's users by their password hash; an anonymous session as the file allows.

    A user name given MAX_WRONG_PASSWORDS wrong passwords in a row is refused for LOCKOUT_S,
    even with the right one: each guess costs the attacker a PBKDF2 check already, and this
    leaves a few a minute against a name. (The line's client logs in again after the lockout;
    names not in the file are not counted, so they cannot fill memory.)
    """

    def __init__(self, config: OpcUaConfig, clock: Callable[[], float] = time.monotonic) -> None:
        self.config = config
        self.users = {user.name: user for user in config.users}
        self._clock = clock
        self._wrong: dict[str, int] = {}  # wrong passwords in a row, by known user name
        self._locked_until_s: dict[str, float] = {}

    def get_user(
        self, iserver: Any, username: str | None = None, password: str | None = None, certificate: Any = None
    ) -> User | None:
        if username is None:
            if self.config.anonymous is AnonymousAccess.READ_ONLY:
                return User(role=UserRole.Anonymous)
            return None
        user = self.users.get(username)
        now_s = self._clock()
        if now_s < self._locked_until_s.get(username, -math.inf):
            log.warning("OPC UA: user %r refused: locked out for %.0f s more", username, self._locked_until_s[username] - now_s)
            return None
        if user is None or password is None or not user.password.matches(password):
            log.warning("OPC UA: user %r refused (unknown user or wrong password)", username)
            if user is not None:
                self._count_wrong(username, now_s)
            return None
        self._wrong.pop(username, None)
        log.info("OPC UA: user %r logged in", username)
        return User(role=UserRole.User, name=username)

    def _count_wrong(self, username: str, now_s: float) -> None:
        wrong = self._wrong.get(username, 0) + 1
        if wrong >= MAX_WRONG_PASSWORDS:
            self._locked_until_s[username] = now_s + LOCKOUT_S
            log.warning("OPC UA: user %r locked out for %g s after %d wrong passwords", username, LOCKOUT_S, wrong)
            wrong = 0
        self._wrong[username] = wrong


@dataclass(frozen=True)
class _Variable:
    """A variable of the address space: its node id's name and its OPC UA type."""

    name: str
    kind: ua.VariantType
    initial: Any


_CELL = (
    _Variable("Phase", ua.VariantType.String, Phase.IDLE.value),
    _Variable("Detail", ua.VariantType.String, ""),
    _Variable("EStopped", ua.VariantType.Boolean, False),
    _Variable("Fault", ua.VariantType.Boolean, False),
    _Variable("Ready", ua.VariantType.Boolean, False),
    _Variable("Busy", ua.VariantType.Boolean, False),
    _Variable("Backend", ua.VariantType.String, ""),
    _Variable("Robot", ua.VariantType.String, ""),
    _Variable("Jobs", ua.VariantType.String, []),
    _Variable("LastRefusal", ua.VariantType.String, ""),
)
_CURRENT = (
    _Variable("Active", ua.VariantType.Boolean, False),
    _Variable("RunId", ua.VariantType.Int64, NO_RUN),
    _Variable("Job", ua.VariantType.String, ""),
    _Variable("PartId", ua.VariantType.String, ""),
    _Variable("Stage", ua.VariantType.String, ""),
    _Variable("Iteration", ua.VariantType.Int32, 0),
    _Variable("ErrorPx", ua.VariantType.Double, math.nan),
)
_LAST = (
    _Variable("RunId", ua.VariantType.Int64, NO_RUN),
    _Variable("Job", ua.VariantType.String, ""),
    _Variable("PartId", ua.VariantType.String, ""),
    _Variable("Outcome", ua.VariantType.String, ""),
    _Variable("Reason", ua.VariantType.String, ""),
    _Variable("PlacementErrorMm", ua.VariantType.Double, math.nan),
    _Variable("FinalErrorPx", ua.VariantType.Double, math.nan),
    _Variable("CycleTimeS", ua.VariantType.Double, math.nan),
    _Variable("CellTimeS", ua.VariantType.Double, math.nan),
    _Variable("Iterations", ua.VariantType.Int32, 0),
)


def _number(value: float | None) -> float:
    return math.nan if value is None else float(value)


def cell_values(state: ControllerState, jobs: list[str]) -> dict[str, Any]:
    """The Cell's and Cell.CurrentRun's variables for a state, by node id name."""
    run = state.run
    active = state.phase in MOVING
    return {
        "Cell.Phase": state.phase.value,
        "Cell.Detail": state.detail,
        "Cell.EStopped": state.phase is Phase.ESTOPPED,
        "Cell.Fault": state.phase is Phase.FAULT,
        "Cell.Ready": state.phase in _READY,
        "Cell.Busy": active,
        "Cell.Backend": state.backend,
        "Cell.Robot": state.robot,
        "Cell.Jobs": jobs,
        "Cell.CurrentRun.Active": active,
        "Cell.CurrentRun.RunId": run.run_id if active and run.run_id is not None else NO_RUN,
        "Cell.CurrentRun.Job": (state.job or "") if active else "",
        "Cell.CurrentRun.PartId": (run.part_id or "") if active else "",
        "Cell.CurrentRun.Stage": run.stage.value if active and run.stage is not None else "",
        "Cell.CurrentRun.Iteration": run.iteration if active else 0,
        "Cell.CurrentRun.ErrorPx": _number(run.error_px) if active else math.nan,
    }


def last_run_values(state: ControllerState) -> dict[str, Any] | None:
    """Cell.LastRun's variables once a state says how a run ended; None otherwise."""
    outcome, run = state.last_outcome, state.run
    if outcome is None or run.run_id is None:
        return None
    return {
        "Cell.LastRun.RunId": run.run_id,
        "Cell.LastRun.Job": state.job or "",
        "Cell.LastRun.PartId": run.part_id or "",
        "Cell.LastRun.Outcome": outcome.outcome.value,
        "Cell.LastRun.Reason": outcome.reason,
        "Cell.LastRun.PlacementErrorMm": _number(outcome.placement_error_mm),
        "Cell.LastRun.FinalErrorPx": _number(outcome.final_error_px),
        "Cell.LastRun.CycleTimeS": float(outcome.duration_s),
        "Cell.LastRun.CellTimeS": _number(outcome.cell_time_s),
        "Cell.LastRun.Iterations": outcome.iterations,
    }


class CellOpcUaServer:
    """The OPC UA server of one controller, on its own thread with its own event loop."""

    def __init__(self, controller: CellController, config: OpcUaConfig) -> None:
        self.controller = controller
        self.config = config
        self.endpoint = config.endpoint
        if not log.isEnabledFor(logging.DEBUG):  # asyncua says every node it adds at info: its warnings are enough
            logging.getLogger("asyncua").setLevel(logging.WARNING)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._changed: asyncio.Event | None = None
        self._stop: asyncio.Event | None = None
        self._started = threading.Event()
        self._failure: BaseException | None = None
        self._nodes: dict[str, tuple[Any, ua.VariantType]] = {}
        self._shown: dict[str, Any] = {}
        self._jobs: list[str] = []
        self._jobs_phase: Phase | None = None  # the phase the job list was read in
        self._thread = threading.Thread(target=self._run, name="opcua", daemon=True)

    # -- the thread -------------------------------------------------------------------------

    def start(self) -> str:
        """Start serving; the endpoint's URL (with the port bound, for port 0)."""
        self.controller.state_subscribers.append(self._on_state)  # first: no change is missed while it starts
        self._thread.start()
        if not self._started.wait(START_TIMEOUT_S):
            raise OpcUaError(f"the OPC UA server did not start within {START_TIMEOUT_S:g} s")
        if self._failure is not None:
            raise OpcUaError(f"the OPC UA server could not start on {self.config.endpoint}: {self._failure}")
        return self.endpoint

    def _run(self) -> None:
        try:
            asyncio.run(self._serve())
        except BaseException as exc:  # reported by start(), or logged once it has returned
            self._failure = exc
            if self._started.is_set():
                log.exception("the OPC UA server stopped")
        finally:
            self._started.set()

    def _on_state(self, state: ControllerState) -> None:
        """A subscriber: never blocks, only wakes the publisher."""
        loop, changed = self._loop, self._changed
        if loop is not None and changed is not None:
            try:
                loop.call_soon_threadsafe(changed.set)
            except RuntimeError:
                pass  # the server has stopped: the controller's thread must not fail for it

    def close(self) -> None:
        if self._on_state in self.controller.state_subscribers:
            self.controller.state_subscribers.remove(self._on_state)
        loop, stop = self._loop, self._stop
        if loop is not None and stop is not None:
            try:
                loop.call_soon_threadsafe(stop.set)
            except RuntimeError:
                pass  # the loop closed meanwhile
        self._thread.join(10.0)

    # -- the server -------------------------------------------------------------------------

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._changed, self._stop = asyncio.Event(), asyncio.Event()
        self._changed.set()  # the first state is published as the server starts
        server = await self._server()
        async with server:
            bound = server.bserver.port if server.bserver is not None else self.config.port
            self.endpoint = endpoint_url(self.config.host, bound)
            log.info("OPC UA server on %s", self.endpoint)
            self._started.set()
            await self._publish_until_stopped()

    async def _server(self) -> Server:
        server = Server(user_manager=OpcUaUsers(self.config))
        await server.init()
        server.set_endpoint(self.config.endpoint)
        server.set_server_name("vservo cell")
        await server.set_application_uri("urn:vservo:controller")
        tokens: list[type] = [ua.UserNameIdentityToken]
        if self.config.anonymous is AnonymousAccess.READ_ONLY:
            tokens.append(ua.AnonymousIdentityToken)
        server.set_identity_tokens(tokens)
        if self.config.certificate is not None and self.config.private_key is not None:
            await server.load_certificate(str(self.config.certificate))
            await server.load_private_key(str(self.config.private_key))
            policies = [ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt]
        else:
            policies = [ua.SecurityPolicyType.NoSecurity]
        # asyncua annotates its own ruleset class, but calls only check_validity on whatever it gets.
        server.set_security_policy(policies, permission_ruleset=_Permissions())  # type: ignore[arg-type]
        namespace = await server.register_namespace(NAMESPACE)
        cell = await server.nodes.objects.add_object(_node("Cell", namespace), ua.QualifiedName("Cell", namespace))
        await self._variables(cell, namespace, "Cell", _CELL)
        for name, variables in (("CurrentRun", _CURRENT), ("LastRun", _LAST)):
            node = await cell.add_object(_node(f"Cell.{name}", namespace), ua.QualifiedName(name, namespace))
            await self._variables(node, namespace, f"Cell.{name}", variables)
        await self._methods(cell, namespace)
        await self._show_last_stored_run()
        return server

    async def _variables(self, parent: Any, namespace: int, prefix: str, variables: tuple[_Variable, ...]) -> None:
        for variable in variables:
            node_id = f"{prefix}.{variable.name}"
            node = await parent.add_variable(
                _node(node_id, namespace),
                ua.QualifiedName(variable.name, namespace),
                ua.Variant(variable.initial, variable.kind),
            )
            self._nodes[node_id] = (node, variable.kind)
            self._shown[node_id] = variable.initial

    async def _methods(self, cell: Any, namespace: int) -> None:
        def argument(name: str, kind: ua.VariantType, description: str) -> ua.Argument:
            result = ua.Argument()
            result.Name, result.DataType, result.ValueRank = name, _node(kind.value), -1
            result.Description = ua.LocalizedText(description)
            return result

        start_inputs = [
            argument("JobName", ua.VariantType.String, "the job to run (one of Cell.Jobs)"),
            argument("PartId", ua.VariantType.String, "the part's ID for traceability ('' for none)"),
        ]
        start_outputs = [argument("RunId", ua.VariantType.Int64, "the run started")]
        await cell.add_method(
            _node("Cell.Start", namespace), ua.QualifiedName("Start", namespace), self._start, start_inputs, start_outputs
        )
        await cell.add_method(_node("Cell.Hold", namespace), ua.QualifiedName("Hold", namespace), self._hold, [], [])
        await cell.add_method(_node("Cell.Reset", namespace), ua.QualifiedName("Reset", namespace), self._reset, [], [])

    # -- publishing --------------------------------------------------------------------------

    async def _publish_until_stopped(self) -> None:
        assert self._changed is not None and self._stop is not None
        stop = asyncio.ensure_future(self._stop.wait())
        try:
            while not self._stop.is_set():
                changed = asyncio.ensure_future(self._changed.wait())
                await asyncio.wait({changed, stop}, return_when=asyncio.FIRST_COMPLETED)
                changed.cancel()
                self._changed.clear()
                try:
                    await self._publish(self.controller.state)
                except Exception:  # a store that cannot be read now: the next change tries again
                    log.exception("OPC UA: the cell's state could not be published")
                await asyncio.sleep(PUBLISH_PERIOD_S)
        finally:
            stop.cancel()

    async def _publish(self, state: ControllerState) -> None:
        if state.phase is not self._jobs_phase:  # a job is saved as teaching ends: read the list as the phase changes
            self._jobs_phase = state.phase
            self._jobs = await asyncio.get_running_loop().run_in_executor(None, self._job_names)
        values = cell_values(state, self._jobs)
        values.update(last_run_values(state) or {})
        await self._write(values)

    def _job_names(self) -> list[str]:
        return [job.name for job in ListJobs().answer(self.controller.store) if job.problem is None]

    async def _write(self, values: dict[str, Any]) -> None:
        for node_id, value in values.items():
            if _same(self._shown.get(node_id), value):
                continue
            node, kind = self._nodes[node_id]
            await node.write_value(ua.Variant(value, kind))
            self._shown[node_id] = value

    async def _show_last_stored_run(self) -> None:
        """Cell.LastRun from the store as the server starts: the plant reads the last result across a restart."""
        runs = await asyncio.get_running_loop().run_in_executor(None, lambda: self.controller.store.list_runs(1))
        run = runs[0] if runs else None
        if run is None or run.outcome is None:
            return
        await self._write(
            {
                "Cell.LastRun.RunId": run.id,
                "Cell.LastRun.Job": run.job,
                "Cell.LastRun.PartId": run.part_id or "",
                "Cell.LastRun.Outcome": run.outcome.value,
                "Cell.LastRun.Reason": run.reason or "",
                "Cell.LastRun.PlacementErrorMm": _number(run.placement_error_mm),
                "Cell.LastRun.FinalErrorPx": _number(run.final_error_px),
                "Cell.LastRun.CycleTimeS": _number(run.duration_s),
                "Cell.LastRun.Iterations": sum(int(stage.get("iterations", 0)) for stage in run.stages),
            }
        )

    # -- methods -----------------------------------------------------------------------------

    async def _start(self, parent: ua.NodeId, job: ua.Variant, part_id: ua.Variant) -> ua.CallMethodResult:
        """Cell.Start(JobName, PartId): the page's Start command, through the controller's guards."""
        try:
            command = Start(job_name=job.Value, part_id=part_id.Value or None)
        except CommandRefused as exc:
            return await self._refused("Start", exc, ua.StatusCodes.BadInvalidArgument)
        log.info("OPC UA: Start(%r, part %r)", command.job_name, command.part_id)
        start = functools.partial(self.controller.start, command.job_name, part_id=command.part_id, by_line=True)
        return await self._carry_out("Start", start)

    async def _hold(self, parent: ua.NodeId) -> ua.CallMethodResult:
        """Cell.Hold(): the page's E-STOP: the robot held now, every move refused until Reset."""
        log.warning("OPC UA: Hold")
        return await self._carry_out("Hold", lambda: self.controller.estop("held by the line (OPC UA Hold)"))

    async def _reset(self, parent: ua.NodeId) -> ua.CallMethodResult:
        """Cell.Reset(): the page's Reset."""
        log.info("OPC UA: Reset")
        return await self._carry_out("Reset", lambda: Reset().carry_out(self.controller))

    async def _carry_out(self, name: str, action: Callable[[], Any]) -> ua.CallMethodResult:
        """Carry ``action`` out off the event loop (a start enables the robot's servo power over its link)."""
        result = ua.CallMethodResult()
        try:
            value = await asyncio.get_running_loop().run_in_executor(None, action)
        except VservoError as exc:
            return await self._refused(name, exc, ua.StatusCodes.BadInvalidState)
        except Exception:
            log.exception("OPC UA %s: internal error", name)
            result.StatusCode = ua.StatusCode(ua.UInt32(ua.StatusCodes.BadInternalError))
            return result
        if isinstance(value, int) and not isinstance(value, bool):
            result.OutputArguments = [ua.Variant(value, ua.VariantType.Int64)]
        await self._write({"Cell.LastRefusal": ""})
        return result

    async def _refused(self, name: str, exc: Exception, status: int) -> ua.CallMethodResult:
        log.warning("OPC UA %s refused: %s", name, exc)
        await self._write({"Cell.LastRefusal": f"{name}: {exc}"})
        result = ua.CallMethodResult()
        result.StatusCode = ua.StatusCode(ua.UInt32(status))
        return result


def _same(shown: Any, value: Any) -> bool:
    if isinstance(shown, float) and isinstance(value, float) and math.isnan(shown) and math.isnan(value):
        return True
    return type(shown) is type(value) and shown == value
