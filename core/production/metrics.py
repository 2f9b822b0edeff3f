"""The controller's Prometheus metrics endpoint ([line.metrics] in the cell file).

What the plant's dashboards read of the cell, from what the controller publishes (its
states and camera frames, through the subscribers every client of the controller has)
and, at each scrape, from the robot link's own counters:

    vservo_phase{phase}                      1 for the phase the cell is in, 0 for the others
    vservo_runs_total{outcome}               runs ended, by outcome (placed, missed, fault, e-stopped)
    vservo_placement_error_mm                histogram of the placement measured from the check view
    vservo_cycle_time_seconds                histogram of a run's time from start to end (the PC's clock)
    vservo_cell_time_seconds                 histogram of a run's time on the cell's clock
    vservo_camera_frames_total               camera frames the controller has seen and published
    vservo_servo_cycles_total                servo cycles of every run
    vservo_link_retries_total{kind}          the JRC link's recoveries (BSC retries; Ethernet: connections made again)

Frames per second are ``rate(vservo_camera_frames_total[1m])``, the Prometheus way: a
counter, never a rate the controller would have to average over a window of its own.

prometheus-client (the Prometheus project's own, pure Python, no dependencies) writes the
text exposition format and serves it from one thread; the controller's registry is its own,
never the library's process-wide one, so two controllers in a test never share a count.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Iterator
from wsgiref.simple_server import WSGIServer

from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram, start_http_server
from prometheus_client.core import CounterMetricFamily
from prometheus_client.registry import Collector

from vservo.core.cell.line import MetricsConfig
from vservo.core.production.cell_controller import CellController, FrameView
from vservo.core.production.protocol import ControllerState, Outcome, Phase
from vservo.core.robot.backend import RobotError
from vservo.core.robot.jrc import JrcBackend
from vservo.core.robot.serial_link import SerialLink

log = logging.getLogger("vservo.metrics")

PLACEMENT_BUCKETS_MM = (0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, math.inf)
TIME_BUCKETS_S = (1.0, 2.0, 5.0, 10.0, 20.0, 30.0, 60.0, 120.0, 300.0, math.inf)


class _LinkRetries(Collector):
    """The robot link's recoveries, read from its counters at each scrape."""

    def __init__(self, controller: CellController) -> None:
        self.controller = controller

    def collect(self) -> Iterator[CounterMetricFamily]:
        family = CounterMetricFamily("vservo_link_retries", "the robot link's recoveries, by kind", labels=["kind"])
        backend = self.controller.rig.robot.robot
        if isinstance(backend, JrcBackend):
            link = backend.link
            if isinstance(link, SerialLink):
                try:
                    counters = link.station.counters
                except RobotError:  # not connected now (a lost port): the next scrape reads it again
                    counters = None
                if counters is not None:
                    for kind in ("enq_retries", "text_resends", "naks_received", "naks_sent", "contentions"):
                        family.add_metric([kind], getattr(counters, kind))
            else:
                family.add_metric(["reconnections"], max(0, getattr(link, "connections", 0) - 1))
        yield family


class ControllerMetrics:
    """The metrics of one controller, kept up to date by its subscribers, served over HTTP."""

    def __init__(self, controller: CellController) -> None:
        self.registry = CollectorRegistry(auto_describe=True)
        self.phase = Gauge("vservo_phase", "1 for the phase the cell is in", ["phase"], registry=self.registry)
        self.runs = Counter("vservo_runs", "runs ended, by outcome", ["outcome"], registry=self.registry)
        self.placement = Histogram(
            "vservo_placement_error_mm",
            "placement error measured from the check view (mm)",
            buckets=PLACEMENT_BUCKETS_MM,
            registry=self.registry,
        )
        self.cycle_time = Histogram(
            "vservo_cycle_time_seconds", "a run's time from start to end", buckets=TIME_BUCKETS_S, registry=self.registry
        )
        self.cell_time = Histogram(
            "vservo_cell_time_seconds", "a run's time on the cell's clock", buckets=TIME_BUCKETS_S, registry=self.registry
        )
        self.frames = Counter("vservo_camera_frames", "camera frames seen and published", registry=self.registry)
        self.cycles = Counter("vservo_servo_cycles", "servo cycles of every run", registry=self.registry)
        self.registry.register(_LinkRetries(controller))
        for outcome in (Outcome.PLACED, Outcome.MISSED, Outcome.FAULT, Outcome.ESTOPPED):
            self.runs.labels(outcome.value)  # every kind listed from the start, at 0
        self._lock = threading.Lock()
        self._counted_run: int | None = None  # the last run whose outcome is counted
        self._cycle: tuple[int | None, int] = (None, 0)  # (run, servo cycles counted)
        self._server: WSGIServer | None = None
        self._thread: threading.Thread | None = None
        self._on_state(controller.state)
        controller.state_subscribers.append(self._on_state)
        controller.frame_subscribers.append(self._on_frame)

    def _on_state(self, state: ControllerState) -> None:
        """A subscriber: quick, never blocks (the controller's state lock is held)."""
        with self._lock:
            for phase in Phase:
                self.phase.labels(phase.value).set(1 if state.phase is phase else 0)
            run_id, iteration = state.run.run_id, state.run.iteration
            counted_run, counted = self._cycle
            if run_id != counted_run:
                counted = 0
            if iteration > counted:
                self.cycles.inc(iteration - counted)
                counted = iteration
            self._cycle = (run_id, counted)
            outcome = state.last_outcome
            if outcome is not None and run_id is not None and run_id != self._counted_run:
                self._counted_run = run_id
                self.runs.labels(outcome.outcome.value).inc()
                self.cycle_time.observe(outcome.duration_s)
                if outcome.placement_error_mm is not None and math.isfinite(outcome.placement_error_mm):
                    self.placement.observe(outcome.placement_error_mm)
                if outcome.cell_time_s is not None:
                    self.cell_time.observe(outcome.cell_time_s)

    def _on_frame(self, view: FrameView) -> None:
        self.frames.inc()

    def serve(self, config: MetricsConfig) -> tuple[str, int]:
        """Serve the metrics on http://host:port/metrics; the address bound (port 0: a free one)."""
        self._server, self._thread = start_http_server(config.port, addr=config.host, registry=self.registry)
        host, port = self._server.server_address[:2]
        log.info("metrics on http://%s:%d/metrics", host, port)
        return str(host), int(port)

    def close(self) -> None:
        if self._server is not None:
            self._server.shutdown()
            self._server.server_close()
        if self._thread is not None:
            self._thread.join(5.0)
