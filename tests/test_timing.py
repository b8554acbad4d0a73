"""The stage timer: laps land in the right stage of the right cycle, repeated laps accumulate, and stages
that did not run are left out."""

from __future__ import annotations

import math

import numpy as np
import pytest

from engine.timing import PAPER_TABLE1_MS, STAGES, StageTimer, summarize_us


class FakeClock:
    def __init__(self) -> None:
        self.t = 100.0

    def now_s(self) -> float:
        return self.t


def test_laps_accumulate_per_stage_and_cycle() -> None:
    clock = FakeClock()
    timer = StageTimer(clock.now_s, max_cycles=3)
    timer.start()
    clock.t += 0.5
    timer.lap("I.acquire")
    clock.t += 0.25
    timer.lap("IV.upload")
    clock.t += 0.125
    timer.lap("IV.upload")  # a second upload in the same cycle adds up
    timer.cycle = 1
    clock.t += 2.0
    timer.lap("II.detect")
    timer.record("III.solve", 0.75)
    assert timer.cycle_dict(0) == {"I.acquire": 0.5, "IV.upload": 0.375}
    assert timer.cycle_dict(1) == {"II.detect": 2.0, "III.solve": 0.75}
    assert timer.cycle_dict(2) == {}
    d = timer.durations_s
    assert d.shape == (3, len(STAGES)) and d[0, STAGES.index("IV.upload")] == 0.375
    assert math.isnan(d[2, 0])
    timer.reset()
    assert timer.cycle == 0 and all(timer.cycle_dict(c) == {} for c in range(3))


def test_summaries_and_the_paper_table_use_the_stage_names() -> None:
    stats = summarize_us({"II.detect": [1e-6, 2e-6, 3e-6], "nope": [1.0]})
    assert set(stats) == {"II.detect"}
    assert stats["II.detect"]["median_us"] == pytest.approx(2.0) and stats["II.detect"]["n"] == 3
    for problem in PAPER_TABLE1_MS.values():
        assert set(problem) <= set(STAGES)
    assert np.isclose(PAPER_TABLE1_MS["32x64"]["III.solve"], 0.100)
