"""Replay timing and the stage chart (app/replay.py, app/stage_chart.py), on a clock the test turns."""

from __future__ import annotations

import numpy as np
import pytest

from vservo.app.replay import ReplayClock, ReplayTimeline
from vservo.app.stage_chart import STAGE_BGR, stage_chart
from vservo.core.production.protocol import RunEntry
from vservo.core.production.protocol.commands import StageCount


def run_with_stages(*stages: tuple[str, int]) -> RunEntry:
    return RunEntry(id=1, job="demo", backend="sim", started_at=0.0, stages=tuple(StageCount(*s) for s in stages))


def _cycles(times_s):
    return [{"time_s": t, "error_px": 100.0 / (k + 1), "bMe": np.eye(4).tolist()} for k, t in enumerate(times_s)]


class FakeTime:
    """The wall clock, turned by the test: no test waits for real time."""

    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_real_clock_timestamps_play_as_recorded():
    timeline = ReplayTimeline.from_cycles(_cycles([5.0, 5.05, 5.10, 5.30]), run_duration_s=2.0)
    assert timeline.times_s == pytest.approx([0.0, 0.05, 0.10, 0.30])
    assert [timeline.index_at(t) for t in (0.0, 0.049, 0.05, 0.2, 9.0)] == [0, 0, 1, 2, 3]


def test_a_simulated_clock_is_scaled_to_the_runs_duration():
    # The simulated cell records 2 s per cycle while the run took 12 s for 200 cycles.
    timeline = ReplayTimeline.from_cycles(_cycles(np.arange(201) * 2.0), run_duration_s=12.0)
    assert timeline.duration_s == pytest.approx(12.0) and timeline.times_s[100] == pytest.approx(6.0)


def test_play_pause_seek_and_speed():
    now = FakeTime()
    clock = ReplayClock(ReplayTimeline.from_cycles(_cycles(np.arange(11) * 0.1), None), now=now)
    assert clock.index() == 0 and not clock.playing
    clock.play()
    now.now += 0.35
    assert clock.index() == 3 and clock.until_next_s() == pytest.approx(0.05)
    clock.pause()
    now.now += 5.0
    assert clock.index() == 3 and clock.until_next_s() is None
    clock.seek(8)
    assert clock.index() == 8 and not clock.playing
    clock.set_speed(2.0)
    clock.play()
    now.now += 0.15  # 0.3 s of the recording at 2x: past its end
    assert clock.index() == 10 and not clock.playing  # at the end
    clock.play()  # again from the start
    assert clock.index() == 0 and clock.playing
    with pytest.raises(ValueError, match="replay speed must be positive, got 0"):
        clock.set_speed(0)


def test_the_stage_chart_draws_each_stage_in_its_colour_and_share():
    image = stage_chart(run_with_stages(("1A", 30), ("3", 10)))
    rows = [np.all(image == STAGE_BGR[stage], axis=2) for stage in ("1A", "3")]
    widths = [int(row.sum(axis=1).max()) for row in rows]
    assert widths[0] == pytest.approx(3 * widths[1], rel=0.05)
    assert stage_chart(run_with_stages()).shape[1] == image.shape[1]
