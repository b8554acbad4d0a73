"""Injected faults: each ends the shot in a defined state (fault recorded with its reason, atoms held, the
card back at or looping in a hold waveform), the engine lives on, and the next shot works once it clears."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import INJECTED_FAULTS
from drivers.sim.lab import SimLab, build_sim_lab
from engine.config import SystemConfig
from engine.engine import Engine
from engine.records import Outcome
from sim_signals import chain_config


def chain(**faults: object) -> SystemConfig:
    """A 24-trap chain, lossless, with 2-slot segments so a plan streams through several of them."""
    data = chain_config(24).model_dump()
    data["sim"].update(lossless=True, seed=5, faults={**data["sim"]["faults"], **faults})
    data["awg"].update(waveforms_per_segment=2)
    return SystemConfig.model_validate(data)


@pytest.fixture(scope="module")
def rig() -> tuple[Engine, SimLab]:
    config = chain()
    devices, lab = build_sim_lab(config)
    return Engine(config, devices, lab=lab), lab


def healthy_shot(engine: Engine) -> None:
    engine.apply(chain())
    for _ in range(5):
        record = engine.run_shot()
        assert record.outcome in (Outcome.SUCCESS, Outcome.UNSOLVABLE), record.fault
        if record.outcome is Outcome.SUCCESS:
            assert record.lab_report["target_filled"]
            return
    raise AssertionError("no solvable shot in 5 tries")


@pytest.mark.parametrize(
    ("faults", "reason"),
    INJECTED_FAULTS,
)
def test_fault_ends_the_shot_defined_and_clears(rig, faults: dict, reason: str) -> None:
    engine, lab = rig
    engine.apply(chain(**faults))
    record = engine.run_shot()
    assert record.outcome is Outcome.FAULT
    assert reason in (record.fault or "")
    atoms_after_fault = lab.world.n_atoms
    # the card holds the atoms: at idle (the hold waveform) or looping a failsafe step, never stopped
    step = lab.awg.current_step()
    lay = engine._p.streamer.layout  # noqa: SLF001 - the test checks the card's real state
    assert lay.is_idle_step(step) or lay.is_failsafe_step(step)
    lab.awg.clock.advance(0.01)  # time passes: a held atom stays held (lossless)
    assert lab.world.n_atoms == atoms_after_fault
    healthy_shot(engine)


def test_late_uploads_underrun_into_the_failsafe_and_still_fill_the_target(rig) -> None:
    engine, lab = rig
    engine.apply(chain(upload_delay_s=200e-6))  # 2 slots play in 20 us; each upload now takes > 200 us
    underruns = 0
    for _ in range(6):
        record = engine.run_shot()
        if record.outcome is Outcome.UNSOLVABLE:
            continue
        assert record.outcome is Outcome.SUCCESS, record.fault
        assert record.lab_report["target_filled"]  # the failsafe paused the moves instead of dropping atoms
        underruns += sum(c.underruns for c in record.cycles)
    assert underruns > 0
    healthy_shot(engine)


def test_a_bad_config_leaves_the_running_one_in_force(rig) -> None:
    engine, lab = rig
    healthy_shot(engine)
    before = engine.config
    bad = chain().model_dump()
    bad["waveforms"]["shape"] = "tanh"
    bad["waveforms"]["shape_sharpness"] = 40.0  # too sharp for the simulated AWG to decode
    with pytest.raises(Exception, match="shape_sharpness"):
        engine.apply(SystemConfig.model_validate(bad))
    assert engine.config is before
    healthy_shot(engine)
    assert np.all(lab.world.occupancy()[engine.target])
