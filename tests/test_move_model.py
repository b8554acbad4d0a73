"""The one move model (``engine/move_model.py``) as the validator and the simulated world use it.

Crossed AODs make a tweezer at every intersection of their tones. The issue's minimal case: ``EXTRACT
y=[0,4] x=[0,5]`` leaves an empty tweezer at (0,5); an x shift brings it onto the atom at (0,4); a y shift
moves it on at full depth. The validator must reject that plan, and the simulated lab, playing the plan's
real waveforms, must drag the atom. Every planner's plans capture nothing.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.awg import SimAWG
from drivers.sim.clock import SimClock
from drivers.sim.decode import SampleDecoder
from drivers.sim.world import World
from engine.devices import StepInfo
from engine.operations import EXTRACT, IMPLANT, SHIFT, Operations, Plan
from engine.solvers import Solver
from engine.solvers.validate import InvalidPlan, replay, validate
from engine.targets import centre_target, rectangle_target
from engine.waveforms import WaveformBank
from sim_signals import grid_config

NX = NY = 8
CFG = grid_config(NX, NY, awg={"upload_jitter_s": 0.0})


def _flat(r: int, c: int) -> int:
    return r * NX + c


def minimal_drag_plan() -> tuple[Plan, np.ndarray]:
    """Atoms at (0,0), (4,0), (4,5) are picked; the atom at (0,4) is not meant to move."""
    occ = np.zeros((NY, NX), dtype=bool)
    for r, c in [(0, 0), (4, 0), (4, 5), (0, 4)]:
        occ[r, c] = True
    ops = Operations(nx=NX, ny=NY)
    ops.append(EXTRACT, [0, 4], [0, 5])
    ops.append(SHIFT, [0, 4], [0, 5], [0, 0], [0, -1])  # the empty tweezer (0,5) arrives over (0,4)
    ops.append(SHIFT, [0, 4], [0, 4], [1, 1], [0, 0])  # and moves on, at full depth
    ops.append(IMPLANT, [1, 5], [0, 4])
    steps = [(_flat(4, 5), _flat(4, 4)),  # slot 1 (x shift)
             (_flat(0, 0), _flat(1, 0)), (_flat(4, 4), _flat(5, 4)), (_flat(4, 0), _flat(5, 0))]  # slot 2 (y)
    return Plan(steps=np.array(steps, dtype=np.int32), operations=ops), occ


def test_validator_rejects_the_minimal_drag() -> None:
    plan, occ = minimal_drag_plan()
    report = replay(plan.operations, occ, trap_source="slm")
    assert report.captures == 1 and report.dragged == 1
    assert report.occupancy[1, 4] and not report.occupancy[0, 4]  # the model drags it to (1,4)
    with pytest.raises(InvalidPlan, match=r"slot 1: .*empty tweezer .* row 0, col 4 and captures it"):
        validate(plan, occ, np.zeros_like(occ), trap_source="slm")


def test_a_plan_whose_moves_account_for_the_drag_is_accepted() -> None:
    plan, occ = minimal_drag_plan()
    steps = plan.steps.tolist()
    steps.insert(2, [_flat(0, 4), _flat(1, 4)])  # the plan says: the atom at (0,4) moves down with the batch
    accounted = Plan(steps=np.array(steps, dtype=np.int32), operations=plan.operations)
    report = validate(accounted, occ, np.zeros_like(occ), trap_source="slm")
    assert report.captures == 1 and report.occupancy[1, 4]


def test_a_capture_released_in_place_is_still_a_disturbance() -> None:
    """An empty tweezer arrives over an atom and ramps down there: the atom ends where it was, but it was
    taken and put back (two transfers) by a plan whose moves do not touch it."""
    occ = np.zeros((NY, NX), dtype=bool)
    occ[0, 0] = occ[0, 2] = True
    ops = Operations(nx=NX, ny=NY)
    ops.append(EXTRACT, [0], [0, 1])
    ops.append(SHIFT, [0], [0, 1], [0], [1, 1])
    ops.append(IMPLANT, [0], [1, 2])
    plan = Plan(steps=np.array([[_flat(0, 0), _flat(0, 1)]], dtype=np.int32), operations=ops)
    with pytest.raises(InvalidPlan, match="captures it"):
        validate(plan, occ, np.zeros_like(occ), trap_source="slm")


def test_the_simulated_lab_drags_the_atom_from_the_real_waveforms() -> None:
    plan, occ = minimal_drag_plan()
    samples = WaveformBank(CFG).render_slots(plan.operations)
    clock = SimClock()
    world = World(CFG, clock=clock, lossless=True)
    world.set_occupancy(occ)
    awg = SimAWG(world, clock, CFG)
    silence = np.zeros((CFG.waveforms.slot_samples, 2), np.int16)
    awg.write_segment(0, samples)
    awg.write_segment(1, silence)
    awg.write_step(0, StepInfo(segment=0, next_step=1))
    awg.write_step(1, StepInfo(segment=1, next_step=1))
    awg.start(0)
    clock.advance(10 * CFG.waveforms.slot_duration_s)
    awg.sync()
    truth = world.occupancy()
    expected = np.zeros_like(occ)
    for r, c in [(1, 0), (5, 0), (5, 4), (1, 4)]:  # (1,4): the dragged atom
        expected[r, c] = True
    assert np.array_equal(truth, expected)
    c = world.counters
    assert c.captured == 1 and c.dragged == 1 and c.lost == 0
    assert c.transfers == 2 * 4  # three pick-ups, one capture, four implants


def _decoded(ops: Operations):
    return SampleDecoder(CFG).decode(WaveformBank(CFG).render_slots(ops))


@pytest.mark.parametrize("lossless", [True, False])
def test_world_rules_on_decoded_samples_match_the_reference(lossless: bool) -> None:
    """Capture on arrival, drag, and a loaded tweezer meeting a static atom, from decoded samples, in the
    world's kernels and its numpy reference (same random numbers when losses are on)."""
    plan, occ = minimal_drag_plan()
    collide = Operations(nx=NX, ny=NY)
    collide.append(EXTRACT, [6], [0])
    collide.append(SHIFT, [6], [0], [0], [1])  # loaded, onto the atom at (6,1)
    collide.append(IMPLANT, [6], [1])
    occ_collide = occ.copy()
    occ_collide[6, 0] = occ_collide[6, 1] = True
    cfg = CFG.model_copy(update={"sim": CFG.sim.model_copy(update={"survival_transfer": 0.7, "survival_step": 0.8})})
    for ops, start in [(plan.operations, occ), (collide, occ_collide)]:
        decoded = _decoded(ops)
        worlds = [World(cfg, rng=np.random.default_rng(5), lossless=lossless, reference=ref) for ref in (False, True)]
        for w in worlds:
            w.set_occupancy(start)
            w.apply_segment(decoded)
        fast, ref = worlds
        assert np.array_equal(fast.occupancy(), ref.occupancy())
        assert fast.counters.as_dict() == ref.counters.as_dict()
    if lossless:  # the physics, checked against what the rules say
        fast, _ = worlds
        assert fast.counters.lost_collision == 2 and not fast.occupancy()[6, :2].any()
        w = World(cfg, lossless=True)
        w.set_occupancy(occ)
        w.apply_segment(_decoded(plan.operations))
        assert w.counters.captured == 1 and w.counters.dragged == 1 and w.occupancy()[1, 4]


def _band_or_rectangle(ny: int, nx: int, n_atoms: int, algorithm: str, seed: int) -> np.ndarray:
    if algorithm.startswith("red-rec") or seed % 2:
        return centre_target(nx=nx, ny=ny, count=max(1, int(0.6 * n_atoms) // nx) * nx)
    rows = min(ny, int(np.sqrt(0.6 * n_atoms)))
    cols = min(nx, int(0.6 * n_atoms) // rows)
    return rectangle_target(nx=nx, ny=ny, row0=(ny - rows) // 2, col0=(nx - cols) // 2, rows=rows, cols=cols)


@pytest.mark.parametrize(
    ("algorithm", "objective"),
    [("red-rec", "slots"), ("red-rec-wide", "slots"), ("aod-parallel", "slots"), ("aod-parallel", "transfers"),
     ("assignment", "slots"), ("exact-1d", "slots")],
)  # fmt: skip
def test_random_plans_from_every_planner_capture_nothing(algorithm: str, objective: str) -> None:
    """Several sizes and fill fractions: every plan is valid under the complete model with zero captures
    (exact-1d plans single rows: an AOD chain and a row of static traps)."""
    if algorithm == "exact-1d":
        cases = [(1, nx, source) for nx in (16, 33, 64) for source in ("aod", "slm")]
    else:
        cases = [(ny, nx, "slm") for ny, nx in [(8, 8), (16, 32), (12, 20)]]
    n_checked = 0
    for ny, nx, source in cases:
        solver = Solver(nx=nx, ny=ny, algorithm=algorithm, trap_source=source, objective=objective)
        for fill in (0.45, 0.6, 0.75):
            for seed in range(4):
                occ = np.random.default_rng(1000 * nx + 10 * seed + int(100 * fill)).random((ny, nx)) < fill
                if ny == 1:
                    target = centre_target(nx=nx, ny=1, count=max(1, int(occ.sum())))
                else:
                    target = _band_or_rectangle(ny, nx, int(occ.sum()), algorithm, seed)
                solver.check_target(target)
                solver.solve_moves(occ, target)
                report = validate(solver.batch(), occ, target, trap_source=source)
                assert report.captures == 0
                n_checked += 1
    assert n_checked == 12 * len(cases)
