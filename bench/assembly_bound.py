"""``llrs bench assembly-bound``: what an idealised planner could reach on a ``llrs bench assembly`` cell.

An optimistic **reference, not a success figure**: no real plan beats it per cycle, because it leaves out
everything that makes planning hard. Each rearrangement cycle it sees the true occupancy (no detection error,
no exposure blur), fills every hole of the target with one spare atom by a minimum-cost assignment (scipy's
``linear_sum_assignment`` over the expected atoms lost per route), and moves every atom at once on its own
interstitial route, as if each had its own tweezer (no AOD product sets, no tone crossings, no groups played
one after the other). Atoms already in the target are never touched. Comparing a planner's ``llrs bench
assembly`` row with this one says how much of the gap to a target is planning within a cycle and how much is
physics. It is optimal per cycle, not over a shot: a bulk planner that loses more atoms in its first cycle but
packs the spare atoms against the target (red-rec's column shifts) filled as often at 0.985/0.985
(docs/benchmarks.md, "Issue 13: the bound"), so a target above the bound needs less loss or a different
strategy across cycles, not a better plan of each cycle.

What it charges is the simulated world's loss model (``drivers/sim/world.py``) for the routes the interstitial
repair planner plays (``engine/solvers/interstitial.py``):

- every moved atom is extracted and implanted once: ``survival_transfer`` twice;
- a route of Manhattan length ``d`` sites is ``2 d`` half-site slots when the atom changes both row and column
  (half a site into a row channel, along it, along a column channel, half a site onto the hole), ``2 d + 2``
  when it stays in its row or column (into a channel and back out): each half-site slot survives with
  ``sqrt(survival_step)``, so the route survives ``survival_step ** (d + same_line)``; the speed model
  (``sim.moves.site_spacing_um``) multiplies both survivals as in the world. A same-line route along an empty
  lattice line could skip the channel's two half steps; the bound does not look for one (one site, 0.1 % at
  0.999);
- vacuum loss ``exp(-t / lifetime)`` for every atom over the cycle's modelled time: one image acquisition
  (``drivers/sim/readout.py``'s model of the configured camera), the host stages replay time charges
  (``engine.timing.REPLAY_HOST_S``) and the playback of the longest route (2 transfer slots and its half-site
  slots, ``waveforms.slot_duration_s`` each: every route of a real plan takes at least that long). Left out,
  which makes the bound more generous: the AWG upload before playback, groups played one after the other;
- imaging loss: every atom survives each image with the cell's image survival;
- passing occupied traps is free (``sim.moves.pass_by_survival`` is not charged, as in the examples).

The shot ends as the engine's does: when an image shows the target filled (success is then the truth after
that image, its own vacuum and imaging loss charged), when fewer spare atoms than holes are left, or after
``max_cycles`` rearrangement cycles. Shots are seeded from ``(seed, j)`` as in ``llrs bench assembly``, but the
loaded arrays are not the simulated world's (its random streams are its own): compare distributions, not
shots. Numpy and scipy only; 200 shots of 32x64 take seconds.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import linear_sum_assignment

from bench.assembly import (
    PROBLEMS,
    Cell,
    add_cell_arguments,
    cell_config,
    csv_list,
    outcome_cells,
    outcome_figures,
    print_rows,
    shot_seeds,
)
from drivers.sim.move_loss import move_survival, trap_parameters
from drivers.sim.readout import readout_time
from engine.targets import build_target
from engine.timing import REPLAY_HOST_S

__all__ = [
    "GRID_PROBLEMS",
    "BoundModel",
    "assign_spares",
    "bound_model",
    "format_bound_table",
    "register",
    "reserve_cost",
    "route_sites",
    "run_bound",
    "run_bound_shot",
    "summarize_bound",
]

#: Interstitial routes need channels on both axes: the 1x64 chain has none.
GRID_PROBLEMS = tuple(p for p in PROBLEMS if not p.startswith("1x"))
#: Host stages between an image and the decision to stop or plan, and those of planning and starting playback.
_IMAGE_STAGES = ("II.detect", "II.threshold")
LOST_CAUSES = ("transfer", "step", "vacuum", "imaging")


@dataclass(frozen=True)
class BoundModel:
    """One cell's array, target and loss model, with the modelled durations of a cycle (seconds)."""

    target: np.ndarray  # bool[ny, nx]
    loading: float
    survival_transfer: float
    survival_step: float  # per one-site step
    lifetime_s: float  # math.inf: no vacuum loss
    image_survival: float
    exposure_s: float
    acquire_s: float  # one image's acquisition: trigger to frame in host memory
    detect_s: float  # host stages from the frame to occupancies
    plan_s: float  # host stages from solving to the start of playback
    slot_s: float
    max_cycles: int
    reserve_sites: int = 0  # first cycle: spare atoms this close to the target charged extra (``reserve_cost``)


def bound_model(cell: Cell, *, loading: float = 0.6, max_cycles: int = 5, reserve_sites: int = 0) -> BoundModel:
    """The cell's model from the same configuration ``llrs bench assembly`` runs (``bench.assembly.cell_config``)."""
    if cell.problem not in GRID_PROBLEMS:
        raise ValueError(f"the bound routes atoms between rows and columns: choose a grid, {', '.join(GRID_PROBLEMS)}")
    cfg = cell_config(cell, loading=loading, max_cycles=max_cycles)
    sim = cfg.sim
    p_transfer, p_step = (1.0, 1.0) if sim.lossless else (sim.survival_transfer, sim.survival_step)
    if not sim.lossless and sim.moves.site_spacing_um is not None:
        wf = cfg.waveforms
        speed = move_survival(
            wf.slot_duration_s, wf.shape, wf.shape_sharpness, sim.moves.site_spacing_um, trap_parameters(sim.moves)
        )
        p_transfer, p_step = p_transfer * speed[0], p_step * speed[1]
    host_image = sum(REPLAY_HOST_S[s] for s in _IMAGE_STAGES)
    readout = readout_time(cfg.camera)
    return BoundModel(
        target=build_target(cfg.target, nx=cfg.array.nx, ny=cfg.array.ny),
        loading=loading,
        survival_transfer=p_transfer,
        survival_step=p_step,
        lifetime_s=math.inf if sim.lossless else sim.vacuum_lifetime_s,
        image_survival=1.0 if sim.lossless else cell.image_survival,
        exposure_s=readout.exposure_s,
        acquire_s=readout.total_s,
        detect_s=host_image,
        plan_s=sum(REPLAY_HOST_S.values()) - host_image,
        slot_s=cfg.waveforms.slot_duration_s,
        max_cycles=max_cycles,
        reserve_sites=reserve_sites,
    )


def route_sites(spare: np.ndarray, holes: np.ndarray) -> np.ndarray:
    """``int[holes, spare]``: one-site steps' worth of loss on the interstitial route from each spare atom to each
    hole (``(row, col)`` rows): the Manhattan length, one more when the two share a row or a column (half a site
    into a channel and half a site back)."""
    dr = np.abs(holes[:, None, 0] - spare[None, :, 0])
    dc = np.abs(holes[:, None, 1] - spare[None, :, 1])
    return dr + dc + ((dr == 0) | (dc == 0))


def reserve_cost(spare: np.ndarray, target: np.ndarray, reserve_sites: int) -> np.ndarray:
    """Extra one-site steps charged to each spare atom the first cycle uses, to keep a reserve near the target for
    the later cycles' repairs: ``reserve_sites + 1 - distance`` for a spare atom ``distance`` sites (Manhattan)
    from the nearest target trap, none beyond. The lead's idealised Monte Carlo suggested it pays; this tool
    measures that it does not (docs/benchmarks.md), hence an option, off by default."""
    if reserve_sites <= 0 or spare.shape[0] == 0:
        return np.zeros(spare.shape[0])
    sites = np.argwhere(target)
    distance = (np.abs(spare[:, None, :] - sites[None, :, :]).sum(axis=2)).min(axis=1)
    return np.maximum(0, reserve_sites + 1 - distance).astype(float)


def assign_spares(cost: np.ndarray) -> np.ndarray:
    """The spare atom (column of ``cost``, holes x spare atoms, at least as many spare atoms) for each hole that
    minimises the total cost."""
    rows, cols = linear_sum_assignment(cost)
    out = np.empty(cost.shape[0], dtype=np.int64)
    out[rows] = cols
    return out


def _survive(rng: np.random.Generator, occ: np.ndarray, p: float) -> int:
    """Every atom of ``occ`` survives with ``p`` (in place); returns the atoms lost."""
    if p >= 1.0 or not occ.any():
        return 0
    lost = occ & (rng.random(occ.shape) >= p)
    occ &= ~lost
    return int(lost.sum())


def run_bound_shot(model: BoundModel, rng: np.random.Generator) -> dict[str, Any]:
    """One shot of the idealised loop; ``filled``, ``rearrangements``, ``time_to_array_s`` and atoms lost by cause."""
    target = model.target
    occ = rng.random(target.shape) < model.loading
    lost = dict.fromkeys(LOST_CAUSES, 0)
    ln_transfer, ln_step = -math.log(model.survival_transfer), -math.log(model.survival_step)
    vacuum_rate = 0.0 if math.isinf(model.lifetime_s) else 1.0 / model.lifetime_s
    readout_s = model.acquire_s - 0.5 * model.exposure_s  # from mid-exposure to the frame in memory
    t_s = 0.0
    rearrangements = 0
    filled = False
    while True:
        # the image shows the atoms there at mid-exposure (the camera's signal is the fraction of the exposure an
        # atom was there, the threshold about half of it); what dies later is seen by the next image only
        lost["vacuum"] += _survive(rng, occ, math.exp(-0.5 * model.exposure_s * vacuum_rate))
        lost["imaging"] += _survive(rng, occ, model.image_survival)
        seen_filled = not (target & ~occ).any()
        t_image_s = t_s + model.acquire_s  # the engine's time to array ends when this image is in memory
        t_s = t_image_s + model.detect_s
        lost["vacuum"] += _survive(rng, occ, math.exp(-(t_s - t_image_s + readout_s) * vacuum_rate))
        if seen_filled:
            filled = not (target & ~occ).any()
            break
        holes = np.argwhere(target & ~occ)  # planned on the truth now: more than any planner knows
        spare = np.argwhere(occ & ~target)
        if rearrangements == model.max_cycles or spare.shape[0] < holes.shape[0]:
            break
        sites = route_sites(spare, holes)
        cost = 2 * ln_transfer + (ln_step or 1.0) * sites  # lossless: the fewest sites
        if rearrangements == 0 and model.reserve_sites:
            cost = cost + (ln_step or 1.0) * reserve_cost(spare, target, model.reserve_sites)[None, :]
        chosen = assign_spares(cost)
        sites = sites[np.arange(holes.shape[0]), chosen]
        src = spare[chosen]
        occ[src[:, 0], src[:, 1]] = False
        u = rng.random((3, holes.shape[0]))
        out_ok = u[0] < model.survival_transfer
        route_ok = out_ok & (u[1] < model.survival_step**sites)
        in_ok = route_ok & (u[2] < model.survival_transfer)
        lost["transfer"] += int((~out_ok).sum() + (route_ok & ~in_ok).sum())
        lost["step"] += int((out_ok & ~route_ok).sum())
        occ[holes[in_ok, 0], holes[in_ok, 1]] = True
        cycle_s = model.plan_s + model.slot_s * (2 + 2 * int(sites.max()))
        t_s += cycle_s
        lost["vacuum"] += _survive(rng, occ, math.exp(-cycle_s * vacuum_rate))
        rearrangements += 1
    return {
        "filled": filled,
        "rearrangements": rearrangements,
        "time_to_array_s": t_image_s if filled else None,
        "lost": lost,
    }


def run_bound(
    cell: Cell, *, shots: int, seed: int = 1, loading: float = 0.6, max_cycles: int = 5, reserve_sites: int = 0
) -> list[dict]:
    """Every shot of a cell, shot ``j`` seeded from ``(seed, j)``."""
    model = bound_model(cell, loading=loading, max_cycles=max_cycles, reserve_sites=reserve_sites)
    return [run_bound_shot(model, np.random.default_rng(s)) for s in shot_seeds(seed, shots)]


def summarize_bound(cell: Cell, shots: Sequence[dict[str, Any]], *, reserve_sites: int = 0) -> dict[str, Any]:
    """One table row: success with its 95 % Wilson interval, cycles, time to array, atoms lost per cycle."""
    return {**cell.label(), "reserve_sites": reserve_sites, **outcome_figures(shots, LOST_CAUSES)}


def format_bound_table(rows: Sequence[dict[str, Any]]) -> str:
    """The rows as a markdown table (what docs/benchmarks.md quotes)."""
    lines = [
        "| problem | loss (transfer/step) | lifetime s | image survival | reserve sites | shots "
        "| bound: success % [95 % CI] "
        "| cycles mean / p90 | time to array ms median / p90 | lost per cycle: " + " / ".join(LOST_CAUSES) + " |",
        "|" + "---|" * 10,
    ]
    for r in rows:
        c = outcome_cells(r, LOST_CAUSES)
        lines.append(
            f"| {r['problem']} | {r['loss']} | {r['lifetime_s']:g} | {r['image_survival']:g} | {r['reserve_sites']} "
            f"| {r['shots']} | {c['success']} | {c['cycles']} | {c['times']} | {c['lost']} |"
        )
    return "\n".join(lines)


def _cmd(args: argparse.Namespace) -> int:
    rows = []
    for problem in csv_list(args.problems):
        for loss in csv_list(args.loss):
            for lifetime in csv_list(args.lifetime):
                for image in csv_list(args.image_survival):
                    cell = Cell(problem, None, loss, float(lifetime), float(image))
                    shots = run_bound(cell, shots=args.shots, seed=args.seed, loading=args.loading,
                                      max_cycles=args.max_cycles, reserve_sites=args.reserve)  # fmt: skip
                    rows.append(summarize_bound(cell, shots, reserve_sites=args.reserve))
    return print_rows(args, rows, format_bound_table)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "assembly-bound", help="what an idealised planner (no AOD constraints) could reach on an assembly cell"
    )
    add_cell_arguments(p, GRID_PROBLEMS)
    p.add_argument(
        "--reserve", type=int, default=0,
        help="first cycle: charge spare atoms within this many sites of the target extra steps (default 0: off)",
    )  # fmt: skip
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    p.set_defaults(func=_cmd)
