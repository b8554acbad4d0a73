"""Interstitial routing (``array.routing: interstitial``, ``engine/routing.py``): the validator, the planners,
the waveforms, the simulated AWG's decoder and the world agree on tweezers that travel between the traps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.sim.decode import SampleDecoder
from drivers.sim.lab import build_sim_lab
from drivers.sim.world import World
from engine.config import SystemConfig, load_config
from engine.engine import Engine
from engine.operations import EXTRACT, IMPLANT, SHIFT, Operations, Plan
from engine.solvers import Solver
from engine.solvers.interstitial import InterstitialRepairPlanner, _groups, group_pairs
from engine.solvers.validate import InvalidPlan, validate
from engine.waveforms import WaveformBank

REPO = Path(__file__).resolve().parents[1]


def _config(**array: object) -> SystemConfig:
    config = load_config(REPO / "examples/grid-16x32.yaml")
    return config.model_copy(update={
        "array": config.array.model_copy(update={"routing": "interstitial", **array}),
        "solver": config.solver.model_copy(update={"algorithm": "repair", "strategy": None}),
        "sim": config.sim.model_copy(update={"lossless": True, "seed": 3}),
    })  # fmt: skip


def _past_an_atom() -> tuple[Plan, np.ndarray, np.ndarray]:
    """Row 0 holds atoms at columns 0 and 1; the atom at 0 goes to column 2, past the one at 1 in the channel
    between rows 0 and 1 (positions: y 0 -> 1 -> 0, x 0 -> 4)."""
    ops = Operations(nx=5, ny=3, half=2)
    steps = []
    ops.append(EXTRACT, [0], [0])
    y, x = 0, 0
    for dy, dx in [(1, 0), (0, 1), (0, 1), (0, 1), (0, 1), (-1, 0)]:
        ops.append(SHIFT, [y], [x], [dy], [dx])
        steps.append((y * 5 + x, (y + dy) * 5 + x + dx))
        y, x = y + dy, x + dx
    ops.append(IMPLANT, [y], [x])
    occ = np.array([[1, 1, 0], [0, 0, 0]], dtype=bool)
    target = np.array([[0, 1, 1], [0, 0, 0]], dtype=bool)
    return Plan(steps=np.array(steps, dtype=np.int32), operations=ops), occ, target


def test_the_validator_accepts_a_route_past_an_occupied_trap() -> None:
    plan, occ, target = _past_an_atom()
    report = validate(plan, occ, target, trap_source="slm")
    assert report.atoms_moved == 1 and report.captures == 0
    assert report.occupancy.tolist() == target.tolist()


def test_the_validator_refuses_a_loaded_tweezer_ending_on_an_occupied_trap() -> None:
    ops = Operations(nx=5, ny=3, half=2)
    ops.append(EXTRACT, [0], [0])
    ops.append(SHIFT, [0], [0], [0], [1])
    ops.append(SHIFT, [0], [1], [0], [1])  # onto the atom at column 1
    plan = Plan(steps=np.array([(0, 1), (1, 2)], dtype=np.int32), operations=ops)
    occ = np.array([[1, 1, 0], [0, 0, 0]], dtype=bool)
    with pytest.raises(InvalidPlan, match="lands on the atom at row 0, col 1"):
        validate(plan, occ, occ, trap_source="slm")


def test_the_validator_refuses_an_implant_in_a_channel() -> None:
    ops = Operations(nx=5, ny=3, half=2)
    ops.append(EXTRACT, [0], [0])
    ops.append(SHIFT, [0], [0], [1], [0])
    ops.append(IMPLANT, [1], [0])
    plan = Plan(steps=np.array([(0, 5)], dtype=np.int32), operations=ops)
    occ = np.array([[1, 0, 0], [0, 0, 0]], dtype=bool)
    with pytest.raises(InvalidPlan, match="ramps down at row 0.5, col 0, between traps"):
        validate(plan, occ, occ, trap_source="slm")


def test_a_chain_cannot_route_between_traps() -> None:
    config = load_config(REPO / "examples/chain-1x64.yaml")
    with pytest.raises(ValueError, match="1D AOD chain"):
        config.array.model_validate({**config.array.model_dump(), "routing": "interstitial"})


@pytest.mark.parametrize("bulk", ["aod-parallel", "red-rec"])
def test_planners_under_interstitial_routing_pass_the_validator(bulk: str) -> None:
    rng = np.random.default_rng(5)
    ny, nx = 10, 16
    target = np.zeros((ny, nx), dtype=bool)
    target[3:7] = True
    for repair_at in (0, 1000):
        solver = Solver(nx=nx, ny=ny, algorithm=bulk, routing="interstitial", repair_algorithm="repair",
                        repair_at_defects=repair_at)  # fmt: skip
        for _ in range(5):
            occ = rng.random((ny, nx)) < 0.6
            solver.solve_moves(occ, target)
            plan = solver.batch()
            report = validate(plan, occ, target, trap_source="slm")
            if plan.algorithm == "repair":  # each spare atom moved once, nothing else touched
                moved = report.atom_pickups > 0
                assert report.max_pickups_per_atom == 1
                assert moved.sum() == int((target & ~occ).sum())
                assert not np.any(moved & target[occ])  # no atom already in the target


def test_the_route_kernel_writes_what_the_plain_python_routes_write() -> None:
    rng = np.random.default_rng(11)
    for _ in range(60):
        ny, nx = (int(v) for v in rng.integers(2, 14, size=2))
        occ = rng.random((ny, nx)) < rng.uniform(0.3, 0.9)
        target = rng.random((ny, nx)) < rng.uniform(0.1, 0.6)
        if occ.sum() < target.sum():
            continue
        plans = []
        for reference in (False, True):
            planner = InterstitialRepairPlanner(nx, ny, reference=reference)
            planner.solve_moves(occ, target)
            plan = planner.batch()
            ops = plan.operations
            plans.append(
                [plan.steps.copy()]
                + [a[: ops.n].copy() for a in (ops.kind, ops.y_site, ops.y_delta, ops.x_site, ops.x_delta)]
            )
        for kernel, reference in zip(*plans, strict=True):
            assert np.array_equal(kernel, reference)
        validate(planner.batch(), occ, target, trap_source="slm")


def test_repairs_in_one_column_move_together_past_the_atoms_between() -> None:
    """Two holes in column 1 of the band (rows 1-3), the spare atoms below it in the same column, the band's
    atom at row 3 in the way: one extract, both atoms moved once, nobody else touched."""
    occ = np.zeros((6, 3), dtype=bool)
    occ[1:4] = True
    occ[1:3, 1] = False
    occ[4:6, 1] = True
    target = np.zeros((6, 3), dtype=bool)
    target[1:4] = True
    solver = Solver(nx=3, ny=6, algorithm="repair", routing="interstitial")
    solver.solve_moves(occ, target)
    plan = solver.batch()
    report = validate(plan, occ, target, trap_source="slm")
    assert int(np.count_nonzero(plan.operations.kind[: plan.n_slots] == EXTRACT)) == 1
    moved = np.flatnonzero(report.atom_pickups)
    assert np.flatnonzero(occ.ravel())[moved].tolist() == [13, 16]  # rows 4 and 5 of column 1


def test_decoded_half_site_positions_match_the_plan() -> None:
    config = _config()
    plan, occ, target = _past_an_atom()
    small = config.model_copy(update={"array": config.array.model_copy(update={"nx": 3, "ny": 2})})
    bank = WaveformBank(small)
    samples = bank.render_slots(plan.operations)
    decoded = SampleDecoder(small).decode(samples)
    ops = plan.operations
    for i in range(len(ops)):
        x_tracks, y_tracks = decoded.slot(i)
        ys, dys, xs, dxs = ops.tones(i)
        assert y_tracks is not None
        assert x_tracks[:, :2].tolist() == [[xs[0], xs[0] + (dxs[0] if ops.kind[i] == SHIFT else 0)]]
        assert y_tracks[:, :2].tolist() == [[ys[0], ys[0] + (dys[0] if ops.kind[i] == SHIFT else 0)]]
    for reference in (False, True):  # the numba kernels and the plain-numpy reference world alike
        world = World(small, lossless=True, reference=reference)
        world.set_occupancy(occ)
        world.apply_segment(decoded)
        assert world.occupancy().tolist() == target.tolist()
        assert world.counters.captured == 0 and world.counters.lost == 0 and world.counters.steps == 6


@pytest.mark.parametrize(("pass_by", "passed_atom_kept"), [(1.0, True), (0.0, False)])
def test_the_world_charges_a_pass_by_only_when_asked(pass_by: float, passed_atom_kept: bool) -> None:
    """``sim.moves.pass_by_survival``: the atom at column 1 is passed once, half a site away (the tweezer ends a
    slot beside it, at position (1, 2) in the channel between rows 0 and 1)."""
    config = _config(nx=3, ny=2)
    sim = config.sim.model_copy(update={
        "lossless": False, "survival_transfer": 1.0, "survival_step": 1.0, "vacuum_lifetime_s": 1e9,
        "moves": config.sim.moves.model_copy(update={"pass_by_survival": pass_by}),
    })  # fmt: skip
    config = config.model_copy(update={"sim": sim})
    plan, occ, target = _past_an_atom()
    decoded = SampleDecoder(config).decode(WaveformBank(config).render_slots(plan.operations))
    world = World(config)
    world.set_occupancy(occ)
    world.apply_segment(decoded)
    assert bool(world.occupancy()[0, 1]) is passed_atom_kept
    assert bool(world.occupancy()[0, 2])  # the carried atom arrives either way
    assert world.counters.lost_pass_by == (0 if passed_atom_kept else 1)


def test_a_lossless_closed_loop_shot_fills_the_target_and_leaves_the_other_atoms() -> None:
    config = _config()
    devices, lab = build_sim_lab(config)
    engine = Engine(config, devices, lab=lab)
    for _ in range(3):
        record = engine.run_shot()
        assert record.lab_report.get("target_filled"), record.outcome
        first = record.cycles[0]
        occ = first.occupancy
        assert first.moves is not None
        moved_from = set(first.moves[:, 0].tolist())
        final = np.asarray(record.cycles[-1].occupancy)
        # every atom not in the plan is where it was
        untouched = np.flatnonzero(occ.ravel())
        untouched = np.array([a for a in untouched if a not in moved_from], dtype=np.int64)
        assert final.ravel()[untouched].all()
        assert first.pickups == first.moves.shape[0]
        # each moved atom's route, recorded after the shot: from its trap to its destination through channels
        assert first.paths is not None
        sources, starts = np.unique(first.paths[:, 0], return_index=True)
        np.testing.assert_array_equal(sources, first.moves[:, 0])
        ends = np.r_[starts[1:], len(first.paths)] - 1
        half_sites = first.paths[:, 1:]
        nx = occ.shape[1]
        np.testing.assert_array_equal(half_sites[starts] // 2 @ [nx, 1], first.moves[:, 0])
        np.testing.assert_array_equal(half_sites[ends] // 2 @ [nx, 1], first.moves[:, 1])
        assert not (half_sites[starts] % 2).any() and not (half_sites[ends] % 2).any()
        inner = np.ones(len(half_sites), dtype=bool)
        inner[starts] = inner[ends] = False
        assert (half_sites[inner] % 2).any(axis=1).all()  # every turn in a channel, none on a trap
    counters = lab.world.counters
    assert counters.captured == 0 and counters.lost == 0


def _band_repairs(rng: np.random.Generator, ny: int, nx: int, holes: int) -> tuple[np.ndarray, np.ndarray]:
    """A full band of target columns with ``holes`` holes, the rest loaded at 0.6 (a repair cycle)."""
    target = np.zeros((ny, nx), dtype=bool)
    target[:, nx // 4 : 3 * nx // 4] = True
    occ = target.copy()
    occ[~target] = rng.random(int((~target).sum())) < 0.6
    occ.flat[rng.choice(np.flatnonzero(target), size=holes, replace=False)] = False
    return occ, target


def test_the_assignment_is_scipys_and_the_kernels_plan_what_python_plans_on_band_repairs() -> None:
    """The repair kernels' assignment gives the pairs scipy's Hungarian solver gave (the planner's assignment
    before it moved into numba), and ``group_pairs`` + ``route_groups`` write the plan ``_groups`` +
    ``_route_group`` write, within the slot and step counts ``group_pairs`` reserves for."""
    from scipy.optimize import linear_sum_assignment

    rng = np.random.default_rng(13)
    ny, nx = 32, 64
    kernel, reference = InterstitialRepairPlanner(nx, ny), InterstitialRepairPlanner(nx, ny, reference=True)
    for trial in range(40):
        occ, target = _band_repairs(rng, ny, nx, int(rng.integers(1, 65)) if trial else 0)
        if trial % 10 == 9:  # a first cycle: ~410 holes
            occ = rng.random((ny, nx)) < 0.6
        kernel.solve_moves(occ, target)
        holes, spare = np.argwhere(target & ~occ), np.argwhere(occ & ~target)
        cost = np.abs(spare[:, None, :] - holes[None, :, :]).sum(axis=2)
        _, spare_of = linear_sum_assignment(cost.T)
        assert np.array_equal(kernel._pairs[: holes.shape[0]], np.concatenate([spare[spare_of], holes], axis=1))
        n_groups, n_slots, n_steps = group_pairs(
            kernel._pairs, holes.shape[0], kernel.py, kernel.px, kernel._grouped, kernel._group_ptr,
            kernel._group_shared,
        )  # fmt: skip
        reference.solve_moves(occ, target)
        plans = []
        for planner in (kernel, reference):
            plan = planner.batch()
            ops = plan.operations
            plans.append(
                [plan.steps] + [a[: ops.n] for a in (ops.kind, ops.y_site, ops.y_delta, ops.x_site, ops.x_delta)]
            )
        for from_kernel, from_python in zip(*plans, strict=True):
            assert np.array_equal(from_kernel, from_python)
        assert n_groups == len(_groups(kernel._pairs[: holes.shape[0]].copy(), (kernel.py, kernel.px)))
        assert kernel.batch().n_slots <= n_slots and kernel.batch().n_steps <= n_steps
        validate(kernel.batch(), occ, target, trap_source="slm")
