"""The simulated world: loading statistics, the loss model, slm tweezer physics and chain conveyor physics."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.clock import SimClock
from drivers.sim.world import World
from sim_signals import chain_config, grid_config


def tracks(*rows: tuple[float, float, float, float]) -> np.ndarray:
    return np.array(rows, dtype=np.float32).reshape(-1, 4)


def static_row(n: int) -> np.ndarray:
    return tracks(*[(k, k, 1, 1) for k in range(n)])


def test_loading_is_bernoulli_and_seeded() -> None:
    cfg = grid_config(32, 32, sim={"loading_probability": 0.6, "seed": 3})
    w = World(cfg)
    fills = [w.load().mean() for _ in range(20)]
    n = 32 * 32 * 20
    assert abs(np.mean(fills) - 0.6) < 4 * np.sqrt(0.6 * 0.4 / n)
    a = World(cfg, rng=np.random.default_rng(5)).load().copy()
    b = World(cfg, rng=np.random.default_rng(5)).load().copy()
    assert np.array_equal(a, b)
    assert w.counters.loaded == pytest.approx(np.sum(fills) * 1024)


def test_occupancy_is_read_only() -> None:
    w = World(grid_config())
    occ = w.load()
    with pytest.raises(ValueError):
        occ[0, 0] = True


def test_vacuum_lifetime_and_lossless() -> None:
    cfg = grid_config(32, 32, sim={"vacuum_lifetime_s": 2.0})
    clock = SimClock()
    w = World(cfg, clock=clock, rng=np.random.default_rng(1))
    w.set_occupancy(np.ones((32, 32), bool))
    clock.advance(2.0)
    frac = w.occupancy().mean()
    assert abs(frac - np.exp(-1)) < 4 * np.sqrt(np.exp(-1) * (1 - np.exp(-1)) / 1024)
    assert w.counters.lost_vacuum == 1024 - w.n_atoms
    lossless = World(cfg, clock=clock, lossless=True)
    lossless.set_occupancy(np.ones((32, 32), bool))
    clock.advance(100.0)
    assert lossless.occupancy().all()


def _extract_move_implant(w: World, row: int, cols: list[int]) -> None:
    """Extract atoms at (row, cols), shift them one row down, implant."""
    xs = [(c, c, 0, 1) for c in cols]
    w.apply_slot(tracks(*xs), tracks((row, row, 0, 1)))
    w.apply_slot(tracks(*[(c, c, 1, 1) for c in cols]), tracks((row, row + 1, 1, 1)))
    w.apply_slot(tracks(*[(c, c, 1, 0) for c in cols]), tracks((row + 1, row + 1, 1, 0)))


def test_tweezer_extract_shift_implant_lossless() -> None:
    w = World(grid_config(8, 6), lossless=True)
    occ = np.zeros((6, 8), bool)
    occ[1, [2, 3, 5]] = True
    occ[1, 7] = True  # not picked: stays
    w.set_occupancy(occ)
    _extract_move_implant(w, 1, [2, 3, 5, 6])  # column 6 has no atom: an empty tweezer does nothing
    want = np.zeros((6, 8), bool)
    want[2, [2, 3, 5]] = True
    want[1, 7] = True
    assert np.array_equal(w.occupancy(), want)
    c = w.counters
    assert (c.transfers, c.steps, c.lost) == (6, 3, 0)
    assert not w.held().any()


def test_held_atoms_are_tracked_between_slots() -> None:
    w = World(grid_config(8, 6), lossless=True)
    occ = np.zeros((6, 8), bool)
    occ[0, 0] = True
    w.set_occupancy(occ)
    w.apply_slot(tracks((0, 0, 0, 1)), tracks((0, 0, 0, 1)))
    assert w.held()[0, 0] and not w.occupancy().any()
    w.apply_slot(tracks((0, 1, 1, 1)), tracks((0, 1, 1, 1)))  # diagonal: one step
    assert w.held()[1, 1] and w.counters.steps == 1
    w.apply_slot(tracks(), tracks())  # tones gone: the atom is dropped
    assert w.n_atoms == 0 and w.counters.lost_dropped == 1


def test_implant_collision_loses_both() -> None:
    w = World(grid_config(8, 6), lossless=True)
    occ = np.zeros((6, 8), bool)
    occ[1, 2] = occ[2, 2] = True
    w.set_occupancy(occ)
    _extract_move_implant(w, 1, [2])
    assert w.n_atoms == 0
    assert w.counters.lost_collision == 2


def test_transfer_and_step_survival_statistics() -> None:
    cfg = grid_config(32, 32, sim={"survival_transfer": 0.9, "survival_step": 0.8})
    w = World(cfg, rng=np.random.default_rng(11))
    occ = np.zeros((32, 32), bool)
    occ[0::2, :] = True  # 512 atoms in even rows, free odd rows below
    w.set_occupancy(occ)
    rows = list(range(0, 32, 2))
    cols = list(range(32))
    w.apply_slot(tracks(*[(c, c, 0, 1) for c in cols]), tracks(*[(r, r, 0, 1) for r in rows]))
    w.apply_slot(tracks(*[(c, c, 1, 1) for c in cols]), tracks(*[(r, r + 1, 1, 1) for r in rows]))
    w.apply_slot(tracks(*[(c, c, 1, 0) for c in cols]), tracks(*[(r + 1, r + 1, 1, 0) for r in rows]))
    p = 0.9 * 0.8 * 0.9
    frac = w.n_atoms / 512
    assert abs(frac - p) < 4 * np.sqrt(p * (1 - p) / 512)
    assert w.occupancy()[1::2].sum() == w.n_atoms  # survivors all moved down one row
    c = w.counters
    assert c.lost == 512 - w.n_atoms == c.lost_transfer + c.lost_step


def test_chain_conveyor_shift_and_fades() -> None:
    w = World(chain_config(8), lossless=True)
    w.set_occupancy(np.array([[1, 1, 0, 1, 0, 0, 1, 0]], bool))
    # block 0..1 shifts right: site 2 fades out (empty), site 0 fades in; atom 3 stays; 6 -> 7
    rows = [(0, 1, 1, 1), (1, 2, 1, 1), (0, 0, 0, 1), (2, 2, 1, 0), (3, 3, 1, 1), (4, 4, 1, 1), (5, 5, 1, 1)]
    rows += [(6, 7, 1, 1), (6, 6, 0, 1), (7, 7, 1, 0)]
    w.apply_slot(tracks(*rows), None)
    assert w.occupancy()[0].astype(int).tolist() == [0, 1, 1, 1, 0, 0, 0, 1]
    assert w.counters.steps == 3 and w.counters.lost == 0


def test_chain_fade_out_with_atom_releases_it() -> None:
    w = World(chain_config(4), lossless=True)
    w.set_occupancy(np.array([[1, 1, 0, 0]], bool))
    w.apply_slot(tracks((0, 1, 1, 1), (0, 0, 0, 1), (1, 1, 1, 0), (2, 2, 1, 1), (3, 3, 1, 1)), None)
    assert w.occupancy()[0].astype(int).tolist() == [0, 1, 0, 0]
    assert w.counters.lost_released == 1
    w.apply_slot(tracks((0, 0, 1, 1)), None)  # no tone at site 1: the atom is lost
    assert w.n_atoms == 0 and w.counters.lost_dropped == 1


def test_chain_idle_keeps_atoms() -> None:
    w = World(chain_config(8), lossless=True)
    occ = w.load().copy()
    for _ in range(5):
        w.apply_slot(static_row(8), None)
    assert np.array_equal(w.occupancy(), occ)
