"""An underrun injected on purpose (``sim.faults.upload_delay_s``): the card loops a failsafe mid-plan, and the
shot record names the atoms that were in flight there. The simulated world, looked at while the card loops the
failsafe, holds exactly those atoms in tweezers at the named sites, and a lossless world loses none of them."""

from __future__ import annotations

import numpy as np

from drivers.sim.lab import build_sim_lab
from engine.engine import Engine
from engine.operations import EXTRACT, IMPLANT, SHIFT, Operations
from engine.records import Outcome, atoms_in_flight
from engine.streaming import SequenceLayout, StreamReport
from engine.timing import StageTimer
from tests.test_sim_upload_delay import grid


def test_the_record_names_the_atoms_the_failsafe_holds_and_none_is_lost() -> None:
    config = grid(upload_delay_s=10e-3)
    devices, lab = build_sim_lab(config)
    engine = Engine(config, devices, lab=lab)
    layout = SequenceLayout.for_config(config)
    held_at_underrun: list[list[int]] = []  # the world's tweezer sites each time the host finds a failsafe looping
    current_step = devices.awg.current_step

    def watched_current_step() -> int:
        step = current_step()
        if layout.is_failsafe_step(step):
            devices.awg.sync()  # the world moves when someone looks (drivers/sim/awg.py)
            held_at_underrun.append(np.flatnonzero(lab.world.held()).tolist())
        return step

    devices.awg.current_step = watched_current_step  # type: ignore[method-assign]  # a probe on the sim card
    in_flight: list[list[list[int]]] = []
    for _ in range(2):
        record = engine.run_shot()
        assert record.outcome is Outcome.SUCCESS, record.fault
        assert record.lab_report["target_filled"]
        for c in record.cycles:
            assert len(c.in_flight) == c.underruns
            assert c.to_dict()["in_flight"] == c.in_flight
            in_flight += c.in_flight
        atoms_detected = record.cycles[0].atoms
        atoms_in_world = sum(row.count("1") for row in record.lab_report["occupancy_rows"])
        assert atoms_in_world == atoms_detected  # lossless: the pauses in the failsafe dropped nobody
    assert in_flight and len(in_flight) == len(held_at_underrun)
    assert any(in_flight)  # some underrun caught atoms mid-move
    for named, world_sites in zip(in_flight, held_at_underrun, strict=True):
        assert sorted(site for _, site in named) == world_sites


def test_in_flight_atoms_follow_their_tweezers_from_their_source_traps() -> None:
    """A hand-made plan on a 3 x 4 grid: extract two atoms of row 0, shift them down, implant."""
    occupancy = np.zeros((3, 4), dtype=bool)
    occupancy[0, [1, 3]] = True
    occupancy[2, 0] = True  # a bystander in a static trap: never in flight
    ops = Operations(nx=4, ny=3)
    ops.append(EXTRACT, [0], [1, 3])
    ops.append(SHIFT, [0], [1, 3], [1], [0, 0])
    ops.append(IMPLANT, [1], [1, 3])
    assert atoms_in_flight(ops, occupancy, 0, chain=False).tolist() == []
    assert atoms_in_flight(ops, occupancy, 1, chain=False).tolist() == [[1, 1], [3, 3]]
    assert atoms_in_flight(ops, occupancy, 2, chain=False).tolist() == [[1, 5], [3, 7]]
    assert atoms_in_flight(ops, occupancy, 3, chain=False).tolist() == []  # implanted: back in static traps


def test_in_flight_atoms_of_a_chain_are_those_carried_off_their_sites() -> None:
    occupancy = np.array([[True, False, True, False, False]])
    ops = Operations(nx=5, ny=1)
    ops.append(SHIFT, [0], [2], [0], [1])
    ops.append(SHIFT, [0], [3], [0], [1])
    assert atoms_in_flight(ops, occupancy, 1, chain=True).tolist() == [[2, 3]]
    assert atoms_in_flight(ops, occupancy, 2, chain=True).tolist() == [[2, 4]]


def test_the_failsafe_continues_each_segment_steadily_and_in_phase() -> None:
    """For every control segment of an underrun plan that has a failsafe, as the card holds them: the failsafe
    starts where the next control segment starts and ends where its own control segment ends (to 2 LSB), so
    falling into it, looping it and leaving it are all phase-continuous; and the simulated AWG's decoder finds it
    steady (no tone moves or switches on or off), so looping it pauses the moves without touching any atom."""
    config = grid(upload_delay_s=10e-3)
    devices, lab = build_sim_lab(config)
    engine = Engine(config, devices, lab=lab)
    layout = SequenceLayout.for_config(config)
    awg = lab.awg  # the simulated card: its memory and its decoder
    joins: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # (control k, its failsafe, control k+1)
    streamer = engine._p.streamer if engine._p is not None else None
    assert streamer is not None
    stream = streamer.stream

    def watched_stream(ops: Operations, timer: StageTimer | None = None) -> StreamReport:
        report = stream(ops, timer)
        if report.underruns:
            for k in range(report.n_segments - 1):
                segments = (layout.control_segment(k), layout.failsafe_segment(k), layout.control_segment(k + 1))
                held = [awg.segment_samples(s) for s in segments]
                assert all(h is not None for h in held)
                joins.append(tuple(np.asarray(h, dtype=np.int32) for h in held))  # type: ignore[arg-type]  # tuple() of 3 types as tuple[ndarray, ...]
        return report

    streamer.stream = watched_stream  # type: ignore[method-assign]  # a probe on the streamer
    record = engine.run_shot()
    assert record.outcome is Outcome.SUCCESS, record.fault
    assert any(np.abs(failsafe).max() > 100 for _, failsafe, _ in joins)  # some failsafe holds moving tweezers
    slot = streamer.bank.slot_samples
    for control, failsafe, following in joins:
        assert failsafe.shape[0] == slot
        assert np.abs(failsafe[-3:] - control[-3:]).max() <= 2  # falls in: continues where the segment ends
        assert np.abs(failsafe[:3] - following[:3]).max() <= 2  # leaves: the next segment starts in phase
        assert awg.decoder.decode(failsafe).stationary  # steady: every tone holds its frequency
        assert awg.decoder.decode(np.tile(failsafe, (3, 1))).stationary  # and stays steady when looped
