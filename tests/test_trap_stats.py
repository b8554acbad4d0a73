"""Per-trap statistics (engine/trap_stats.py) against hand-computed values, the per-atom moves of a plan, and a
trap made lossy on purpose in the simulated lab standing out in the survival map."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.lab import build_sim_lab
from engine.config import SystemConfig
from engine.engine import Engine
from engine.records import CycleRecord, Outcome, ShotRecord, atom_moves, atom_paths
from engine.trap_stats import StatsBook, TrapStatistics

NAN = np.nan


def bits(row: str) -> np.ndarray:
    return np.array([[c == "1" for c in row]])


def cycle(index: int, occupancy: str, moves: list[list[int]] | None, counts: list[float]) -> CycleRecord:
    occ = bits(occupancy)
    return CycleRecord(
        index=index, occupancy=occ, atoms=int(occ.sum()), defects=0,
        moves=None if moves is None else np.array(moves, dtype=np.int32).reshape(-1, 2),
        counts=np.array(counts, dtype=np.float32),
    )


def shot(shot_id: int, cycles: list[CycleRecord], truth: str) -> ShotRecord:
    return ShotRecord(
        shot_id=shot_id, config_digest="d", algorithm="exact-1d", target=bits("0110"), outcome=Outcome.SUCCESS,
        cycles=cycles, lab_report={"occupancy_rows": [truth], "target_filled": True},
    )


def test_atom_moves_follow_each_atom_from_start_to_end() -> None:
    steps = np.array([[0, 1], [1, 2], [5, 4], [7, 8], [8, 7]])
    np.testing.assert_array_equal(atom_moves(steps), [[0, 2], [5, 4]])  # 7 -> 8 -> 7 did not move
    assert atom_moves(np.zeros((0, 2), dtype=np.int32)).shape == (0, 2)
    # a conveyor: the atom ahead steps first, the one behind steps into the site it left
    np.testing.assert_array_equal(atom_moves(np.array([[3, 4], [2, 3]])), [[2, 3], [3, 4]])


def test_statistics_match_hand_counts() -> None:
    stats = TrapStatistics(1, 4, window_shots=2)
    # shot A: atoms at 0 and 2; the plan moves 0 -> 1 and leaves 2; both seen after; the world agrees
    stats.add(shot(0, [cycle(0, "1010", [[0, 1]], [9, 1, 8, 2]), cycle(1, "0110", None, [1, 9, 9, 1])], "0110"))
    # shot B: atoms at 0 and 3 moved to 1 and 2; the one at 2 is not seen after; the world says it is there
    stats.add(shot(1, [cycle(0, "1001", [[3, 2], [0, 1]], [7, 2, 1, 8]), cycle(1, "0100", None, [1, 7, 1, 2])], "0110"))
    maps = stats.maps()
    np.testing.assert_allclose(maps["loading_probability"], [[1.0, 0.0, 0.5, 0.5]])
    np.testing.assert_allclose(maps["survival"], [[NAN, 1.0, 0.5, NAN]])  # counted where the plan left the atom
    np.testing.assert_allclose(maps["defect_rate"], [[NAN, 0.0, 0.5, NAN]])  # target traps only
    np.testing.assert_allclose(maps["disagreement_rate"], [[0.0, 0.0, 0.5, 0.0]])
    np.testing.assert_array_equal(stats.samples()["survival_trials"], [[0, 2, 2, 0]])
    np.testing.assert_array_equal(np.sort(stats.recent_counts()), np.sort([9, 1, 8, 2, 7, 2, 1, 8]))
    np.testing.assert_array_equal(stats.latest_counts, [[7, 2, 1, 8], [1, 7, 1, 2]])
    # the ring keeps the first images of the last `window_shots` shots only: memory does not grow
    stats.add(shot(2, [cycle(0, "0000", None, [0, 0, 0, 0])], "0000"))
    np.testing.assert_array_equal(np.sort(stats.recent_counts()), np.sort([7, 2, 1, 8, 0, 0, 0, 0]))
    assert stats.shots == 3


def test_book_keeps_statistics_per_configuration_and_resets() -> None:
    book = StatsBook()
    record = shot(0, [cycle(0, "1010", None, [1, 2, 3, 4])], "1010")
    book.add(record)
    other = shot(1, [cycle(0, "1111", None, [1, 2, 3, 4])], "1111")
    other.config_digest = "e"
    book.add(other)
    assert book.get("d").shots == 1 and book.get("e").shots == 1  # type: ignore[union-attr]  # both traps were recorded just above
    book.reset("d")
    assert book.get("d") is None and book.get("e") is not None
    book.reset()
    assert book.get("e") is None


def test_a_lossy_trap_stands_out_in_the_survival_map(lossless_chain: SystemConfig) -> None:
    config = lossless_chain.model_copy(
        update={"sim": lossless_chain.sim.model_copy(update={"time": "replay", "seed": 3})}
    )
    devices, lab = build_sim_lab(config)
    engine = Engine(config, devices, lab=lab)
    lossy = 40  # inside the 32-atom centre target (traps 16..47), so plans keep bringing atoms to it
    survival = np.ones((1, 64))
    survival[0, lossy] = 0.97  # per waveform slot an atom sits there
    lab.world.set_trap_survival(survival, seed=5)
    stats = TrapStatistics(1, 64)
    try:
        for _ in range(25):
            stats.add(engine.run_shot())
    finally:
        devices.close()
    measured = stats.maps()["survival"][0]
    trials = stats.samples()["survival_trials"][0]
    assert trials[lossy] >= 10
    assert int(np.nanargmin(measured)) == lossy
    others = np.delete(measured, lossy)
    assert measured[lossy] < 0.9 < np.nanmin(others)
    assert lab.world.counters.lost_trap > 0


def test_trap_survival_hook_checks_its_input(lossless_chain: SystemConfig) -> None:
    devices, lab = build_sim_lab(lossless_chain)
    try:
        with pytest.raises(ValueError, match=r"float\[1, 64\]"):
            lab.world.set_trap_survival(np.ones((2, 64)))
        with pytest.raises(ValueError, match=r"\[0, 1\]"):
            lab.world.set_trap_survival(np.full((1, 64), 1.5))
    finally:
        devices.close()


def test_held_shots_keep_counts_only_while_latest() -> None:
    """2000 held shots of 8192 traps would hold ~200 MB of counts: the service keeps them on the latest only."""
    from server.shot_history import ShotHistory

    history = ShotHistory(2000)  # the service's held shots, which own this bookkeeping
    first, second = (
        ShotRecord(shot_id=i, config_digest="d", algorithm="a", target=np.zeros((1, 4), bool)) for i in range(2)
    )
    for record in (first, second):
        record.cycles.append(CycleRecord(index=0, occupancy=np.zeros((1, 4), bool), atoms=0, defects=0,
                                         counts=np.ones(4, np.float32)))  # fmt: skip
    history.drop_counts_of_older_shots(first)
    assert first.cycles[0].counts is not None
    history.drop_counts_of_older_shots(second)
    assert first.cycles[0].counts is None and second.cycles[0].counts is not None


def test_atom_paths_keep_the_corners_of_a_route_through_the_channels() -> None:
    """Interstitial (positions every half site, 3 traps across: 5 positions): the atom at trap 0 steps into the
    channel below row 0, along it past trap 1, and back up onto trap 2; its corners on the half-site grid."""
    y_x = [(0, 0), (1, 0), (1, 1), (1, 2), (1, 3), (1, 4), (0, 4)]
    steps = np.array([(a[0] * 5 + a[1], b[0] * 5 + b[1]) for a, b in zip(y_x, y_x[1:], strict=False)])
    paths = atom_paths(steps, nx=3, half=2)
    np.testing.assert_array_equal(paths, [[0, 0, 0], [0, 1, 0], [0, 1, 4], [0, 0, 4]])
    np.testing.assert_array_equal(atom_moves(steps, nx=3, half=2), [[0, 2]])  # the same atoms, in the same order


def test_atom_paths_follow_each_atom_of_a_lattice_relay() -> None:
    """Lattice (a position per site, 2 rows of 8 traps): a relay pushes the atom at 3 on to 4 as the one at 2
    takes its place; the atom at 0 goes along row 0 to 1, then down to 9; 7 -> 15 -> 7 stays put.
    Corners are in half sites (2 per site) whatever the routing."""
    steps = np.array([[3, 4], [2, 3], [0, 1], [1, 9], [7, 15], [15, 7]])
    paths = atom_paths(steps, nx=8)
    np.testing.assert_array_equal(paths, [
        [0, 0, 0], [0, 0, 2], [0, 2, 2],  # 0 -> 1 -> 9: one turn
        [2, 0, 4], [2, 0, 6],
        [3, 0, 6], [3, 0, 8],
    ])  # fmt: skip
    np.testing.assert_array_equal(np.unique(paths[:, 0]), atom_moves(steps, nx=8)[:, 0])
    # the bound keeps whole routes, atom after atom: the rest keep only their move
    np.testing.assert_array_equal(atom_paths(steps, nx=8, max_points=5), paths[:5])
    assert atom_paths(np.zeros((0, 2), dtype=np.int32), nx=8).shape == (0, 3)
