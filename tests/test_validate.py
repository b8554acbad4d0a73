"""The plan validator rejects every illegal move of the AOD model with a message naming the slot and rule."""

from __future__ import annotations

import numpy as np
import pytest

from engine.operations import EXTRACT, IDLE, IMPLANT, SHIFT, Operations, Plan
from engine.solvers.validate import InvalidPlan, replay, validate


def grid(rows: list[str]) -> np.ndarray:
    return np.array([[c == "1" for c in r] for r in rows], dtype=bool)


def ops_of(ny: int, nx: int, slots: list[tuple]) -> Operations:
    ops = Operations(nx=nx, ny=ny, capacity=4)
    for kind, ys, xs, *deltas in slots:
        dys, dxs = deltas if deltas else (None, None)
        ops.append(kind, ys, xs, dys, dxs)
    return ops


def test_a_legal_batch_moves_the_product_set_and_counts_pickups() -> None:
    occ = grid(["110", "000", "000"])
    ops = ops_of(3, 3, [(EXTRACT, [0], [0, 1]), (SHIFT, [0], [0, 1], [1], [0, 0]), (IMPLANT, [1], [0, 1])])
    report = replay(ops, occ, trap_source="slm")
    assert np.array_equal(report.occupancy, grid(["000", "110", "000"]))
    assert report.steps == 2 and report.atoms_moved == 2 and report.max_pickups_per_atom == 1 and report.batches == 1


@pytest.mark.parametrize(
    ("occ", "slots", "message"),
    [
        (["10", "10"], [(EXTRACT, [0], [0]), (SHIFT, [0], [0], [1], [0]), (IMPLANT, [1], [0])], "lands on the atom"),
        (["11", "00"], [(EXTRACT, [0], [0, 1]), (SHIFT, [0], [0, 1], [0], [1, 0])], "cross or merge"),
        (["10", "00"], [(EXTRACT, [0], [0]), (SHIFT, [0], [0], [-1], [0])], "leaves the array"),
        (["10", "00"], [(EXTRACT, [0], [0]), (EXTRACT, [0], [0])], "still on"),
        (["10", "00"], [(SHIFT, [0], [0], [1], [0])], "extract first"),
        (["10", "00"], [(EXTRACT, [0], [0]), (SHIFT, [1], [0], [1], [0])], "where the tweezers are"),
        (["10", "00"], [(EXTRACT, [0], [0]), (IDLE, [], [])], "drops them"),
        (["10", "00"], [(EXTRACT, [0], [0])], "still in the tweezers"),
        (["10", "00"], [(EXTRACT, [1, 0], [0])], "strictly ascending"),
    ],
)
def test_illegal_tweezer_plans_are_rejected(occ: list[str], slots: list[tuple], message: str) -> None:
    ops = ops_of(2, 2, slots)
    with pytest.raises(InvalidPlan, match=message):
        replay(ops, grid(occ), trap_source="slm")


@pytest.mark.parametrize(
    ("occ", "xs", "dxs", "message"),
    [
        ("110", [0], [1], "holds an atom"),
        ("101", [0, 2], [1, -1], "merge"),
        ("110", [0, 1], [1, -1], "cross"),
        ("001", [2], [1], "leaves the chain"),
    ],
)
def test_illegal_chain_shifts_are_rejected(occ: str, xs: list[int], dxs: list[int], message: str) -> None:
    ops = ops_of(1, 3, [(SHIFT, [0], xs, [0], dxs)])
    with pytest.raises(InvalidPlan, match=message):
        replay(ops, grid([occ]), trap_source="aod")


def test_chain_block_shift_moves_a_contiguous_block() -> None:
    ops = ops_of(1, 4, [(SHIFT, [0], [0, 1], [0], [1, 1])])
    report = replay(ops, grid(["1100"]), trap_source="aod")
    assert np.array_equal(report.occupancy, grid(["0110"])) and report.steps == 2


def test_validate_checks_target_and_steps_agree() -> None:
    occ = grid(["100"])
    target = grid(["010"])
    ops = ops_of(1, 3, [(SHIFT, [0], [0], [0], [1])])
    good = Plan(steps=np.array([[0, 1]], dtype=np.int32), operations=ops)
    assert validate(good, occ, target, trap_source="aod").target_reached
    wrong_steps = Plan(steps=np.zeros((0, 2), dtype=np.int32), operations=ops)
    with pytest.raises(InvalidPlan, match="different traps"):
        validate(wrong_steps, occ, target, trap_source="aod")
    with pytest.raises(InvalidPlan, match="leaves target traps empty"):
        validate(good, occ, grid(["001"]), trap_source="aod")


def test_validate_follows_each_atom_not_only_the_occupancy() -> None:
    """Two atoms swap corners: the plan's steps give the same traps and the same number of steps as the
    slots, but move each atom somewhere else, so they do not describe what the slots do."""
    occ = grid(["10", "01"])
    ops = ops_of(2, 2, [
        (EXTRACT, [0], [0]), (SHIFT, [0], [0], [0], [1]), (IMPLANT, [0], [1]),  # (0,0) -> (0,1)
        (EXTRACT, [1], [1]), (SHIFT, [1], [1], [0], [-1]), (IMPLANT, [1], [0]),  # (1,1) -> (1,0)
    ])  # fmt: skip
    good = Plan(steps=np.array([[0, 1], [3, 2]], dtype=np.int32), operations=ops)
    assert validate(good, occ, grid(["01", "10"]), trap_source="slm").atoms_moved == 2
    swapped = Plan(steps=np.array([[0, 2], [3, 1]], dtype=np.int32), operations=ops)
    with pytest.raises(InvalidPlan, match=r"the atom from row 0, col 0: the slots move it 1 sites to row 0, col 1"):
        validate(swapped, occ, grid(["01", "10"]), trap_source="slm")


def test_an_atom_picked_up_and_put_back_unmoved_is_rejected() -> None:
    occ = grid(["11", "00"])
    ops = ops_of(2, 2, [(EXTRACT, [0], [0, 1]), (SHIFT, [0], [0, 1], [1], [0, 0]), (SHIFT, [1], [0, 1], [-1], [0, 0]),
                        (IMPLANT, [0], [0, 1])])  # fmt: skip
    steps = np.array([[0, 2], [1, 3], [2, 0], [3, 1]], dtype=np.int32)  # both atoms move: accepted
    validate(Plan(steps=steps, operations=ops), occ, occ, trap_source="slm")
    lazy = ops_of(2, 2, [(EXTRACT, [0], [0, 1]), (IMPLANT, [0], [0, 1])])
    with pytest.raises(InvalidPlan, match="pick up 2 atom"):
        validate(Plan(steps=np.zeros((0, 2), dtype=np.int32), operations=lazy), occ, occ, trap_source="slm")
