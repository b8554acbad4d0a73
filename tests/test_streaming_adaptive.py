"""Control segments that grow (``awg.segment_growth`` up to ``awg.max_waveforms_per_segment``): the card plays
every slot of a long plan once, in order, through segments of the configured sizes, and a host too slow for
the larger segments lands in their failsafes with the atoms held and none lost."""

from __future__ import annotations

import numpy as np
import pytest
from pydantic import ValidationError

from drivers.sim.lab import build_sim_lab
from engine.card_rules import page_aligned_zeros
from engine.config import AWGConfig, SystemConfig
from engine.engine import Engine
from engine.records import Outcome
from engine.solvers import solve
from engine.streaming import SequenceLayout, Streamer
from engine.targets import build_target
from engine.waveforms import WaveformBank
from sim_signals import grid_config

GROWING = {"waveforms_per_segment": 4, "segment_growth": 2.0, "max_waveforms_per_segment": 16,
           "n_segments": 64, "n_steps": 256}


def growing_grid(**sim: object) -> SystemConfig:
    """16 x 12 red-rec into the centre band (plans of about 100 slots) on segments of 4, 4, 8, 16, 16, ... slots."""
    return grid_config(
        16, 12,
        solver={"algorithm": "red-rec"},
        target={"kind": "centre", "count": 16 * 6, "rows": None, "cols": None},
        awg=GROWING,
        sim={"lossless": True, "seed": 3, **sim},
    )


def test_segment_sizes_grow_from_the_first_two_up_to_the_cap() -> None:
    awg = AWGConfig(waveforms_per_segment=4, segment_growth=1.5, max_waveforms_per_segment=12)
    assert awg.control_segment_slots(8) == (4, 4, 6, 9, 12, 12, 12, 12)
    assert AWGConfig(waveforms_per_segment=32).control_segment_slots(4) == (32, 32, 32, 32)
    layout = SequenceLayout(segment_slots=(4, 4, 8, 16))
    assert layout.max_slots == 32
    assert [layout.segments_for(n) for n in (8, 9, 16, 17, 32)] == [2, 3, 3, 4, 4]
    assert layout.segment_span(3, 20) == (16, 4)  # the last segment holds what is left
    assert layout.slots_before_failsafe(layout.failsafe_step(2)) == 16


def test_a_cap_below_the_first_segments_is_refused_saying_which_to_raise() -> None:
    with pytest.raises(ValidationError, match="max_waveforms_per_segment = 16 is below awg.waveforms_per_segment"):
        AWGConfig(waveforms_per_segment=32, max_waveforms_per_segment=16)


def test_a_segment_longer_than_the_cards_memory_partition_is_refused() -> None:
    cfg = growing_grid()
    slot_bytes = WaveformBank(cfg).slot_samples * 2 * 2
    # 64 segments share 64 equal parts: room for 8 slots per part, but the layout grows to 16
    small = cfg.model_copy(update={"awg": cfg.awg.model_copy(update={"max_memory_bytes": 64 * 8 * slot_bytes})})
    devices, _ = build_sim_lab(cfg)
    try:
        with pytest.raises(ValueError, match="longer than one of the 64 equal parts"):
            Streamer(small, WaveformBank(small), devices.awg, devices.clock)
    finally:
        devices.close()


def test_a_long_plan_plays_every_slot_once_in_order_through_growing_segments() -> None:
    cfg = growing_grid(time="replay")
    arr = cfg.array
    target = build_target(cfg.target, nx=arr.nx, ny=arr.ny)
    occupancy = np.random.default_rng(0).random((arr.ny, arr.nx)) < 0.6
    ops = solve(occupancy, target, algorithm="red-rec", trap_source="slm").operations
    devices, _ = build_sim_lab(cfg)
    try:
        awg = devices.awg
        bank = WaveformBank(cfg)
        streamer = Streamer(cfg, bank, awg, devices.clock)
        layout = streamer.layout
        assert layout.segment_slots[:5] == (4, 4, 8, 16, 16)
        n_segments = layout.segments_for(len(ops))
        assert len(ops) > 48 and n_segments >= 5  # through the grown segments
        streamer.program_idle()
        awg.start(layout.idle_step)
        awg.clear_log()
        report = streamer.stream(ops)
        assert report.n_segments == n_segments
        controls = {layout.control_step(k): k for k in range(layout.n_control)}
        played = [controls[r.step] for r in awg.played_steps() if r.step in controls]
        assert played == list(range(n_segments))  # each control segment once, in order (failsafes between hold)
        sizes = [awg.segment_samples(layout.control_segment(k)).shape[0] // bank.slot_samples for k in played]
        assert sizes == [layout.segment_span(k, len(ops))[1] for k in played]
        on_card = np.concatenate([awg.segment_samples(layout.control_segment(k)) for k in played])
        whole = page_aligned_zeros((len(ops) * bank.slot_samples, bank.n_channels), np.int16)
        keys = np.zeros(bank.max_keys(len(ops)), dtype=np.int64)
        bank.lookup(ops, 0, len(ops), keys)
        bank.render(0, len(ops), whole)
        np.testing.assert_array_equal(on_card, whole)  # the plan rendered in one piece, sample for sample
        decoded, expected = awg.decoder.decode(on_card), awg.decoder.decode(whole)
        assert decoded.n_slots == len(ops)
        assert [decoded.describe(i) for i in range(len(ops))] == [expected.describe(i) for i in range(len(ops))]
    finally:
        devices.close()


def test_a_stalled_host_lands_in_the_failsafe_of_a_grown_segment_with_every_atom_held() -> None:
    """Every upload 5 ms late (``sim.faults.upload_delay_s``): the card falls into failsafes, among them those
    after the grown segments; the record names the atoms in flight there, and the lossless world keeps them all."""
    cfg = growing_grid(faults={"upload_delay_s": 5e-3})
    devices, lab = build_sim_lab(cfg)
    try:
        engine = Engine(cfg, devices, lab=lab)
        layout = SequenceLayout.for_config(cfg)
        after: list[int] = []  # slots played when the host found the card in a failsafe
        current_step = devices.awg.current_step

        def watched_current_step() -> int:
            step = current_step()
            if layout.is_failsafe_step(step):
                after.append(layout.slots_before_failsafe(step))
            return step

        devices.awg.current_step = watched_current_step  # type: ignore[method-assign]  # a probe on the sim card
        for _ in range(2):
            record = engine.run_shot()
            assert record.outcome is Outcome.SUCCESS, record.fault
            assert record.lab_report["target_filled"]
            atoms_in_world = sum(row.count("1") for row in record.lab_report["occupancy_rows"])
            assert atoms_in_world == record.cycles[0].atoms  # the pauses dropped nobody
            for c in record.cycles:
                assert len(c.in_flight) == c.underruns
        grown_ends = set(layout.slot_offsets[4:])  # failsafes that follow a 16-slot segment
        assert after and grown_ends & set(after)
    finally:
        devices.close()
