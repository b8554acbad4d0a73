"""The upload-delay fault knob at the default 32 waveforms per segment: late uploads underrun plans that stream
through more than two segments (the card falls into the failsafe, holds the tweezers, resumes, and the target
is still filled); a plan short enough for the short path is uploaded before playback starts, so there the
delay can only show as upload time, never as an underrun."""

from __future__ import annotations

import pytest

from drivers.sim.lab import build_sim_lab
from engine.config import SystemConfig
from engine.engine import Engine
from engine.records import Outcome
from sim_signals import chain_config, grid_config

WAVEFORMS_PER_SEGMENT = SystemConfig().awg.waveforms_per_segment


def grid(upload_delay_s: float) -> SystemConfig:
    """A 16 x 12 grid filling its centre band: red-rec plans of about 100 slots, several segments each."""
    return grid_config(
        16, 12,
        solver={"algorithm": "red-rec"},
        target={"kind": "centre", "count": 16 * 6, "rows": None, "cols": None},
        awg={"waveforms_per_segment": WAVEFORMS_PER_SEGMENT, "n_segments": 64, "n_steps": 256},
        sim={"lossless": True, "seed": 3, "faults": {"upload_delay_s": upload_delay_s}},
    )


@pytest.mark.parametrize("upload_delay_s", [0.2e-3, 10e-3])
def test_late_uploads_underrun_long_plans_at_the_default_segment_size(upload_delay_s: float) -> None:
    assert WAVEFORMS_PER_SEGMENT == 32
    config = grid(upload_delay_s)
    devices, lab = build_sim_lab(config)
    engine = Engine(config, devices, lab=lab)
    underruns = 0
    for _ in range(3):
        record = engine.run_shot()
        assert record.outcome is Outcome.SUCCESS, record.fault
        assert record.lab_report["target_filled"]  # the failsafe paused the moves; no atom was dropped
        assert max(c.n_slots for c in record.cycles) > 2 * WAVEFORMS_PER_SEGMENT  # the segmented path
        underruns += sum(c.underruns for c in record.cycles)
    assert underruns > 0


def test_a_short_plan_shows_the_delay_as_upload_time_not_as_underruns() -> None:
    def chain(upload_delay_s: float) -> SystemConfig:
        return chain_config(24, awg={"waveforms_per_segment": WAVEFORMS_PER_SEGMENT, "n_segments": 16, "n_steps": 64},
                            sim={"lossless": True, "seed": 5, "faults": {"upload_delay_s": upload_delay_s}})

    devices, lab = build_sim_lab(chain(0.0))
    engine = Engine(chain(0.0), devices, lab=lab)

    def upload_s(delay_s: float) -> list[float]:
        engine.apply(chain(delay_s))
        times = []
        for _ in range(4):
            record = engine.run_shot()
            assert sum(c.underruns for c in record.cycles) == 0
            times += [c.stage_s["IV.upload"] for c in record.cycles if 0 < c.n_slots <= 2 * WAVEFORMS_PER_SEGMENT]
        return times

    clean, late = upload_s(0.0), upload_s(10e-3)
    assert clean and late
    assert min(late) > max(clean) + 9e-3  # every short-path upload carries the injected 10 ms
