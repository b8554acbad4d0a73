"""Reference plans of the AOD-parallel planner, stored as digests (``tests/data/aod_parallel_plans.json``).

The planner's kernels are rewritten for readability now and then; every rewrite must give byte-identical
plans. ``plan_digests()`` plans a fixed set of instances (array shapes, target rectangles, loadings, both
objectives, transposed frames included) and digests each plan's slots and steps; ``python
tests/aod_parallel_golden.py`` stores them (run it only on code whose plans are known good), and
``tests/test_solver_aod_parallel.py`` compares against the stored file.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np

from engine.operations import Plan
from engine.solvers import UnsolvableError
from engine.solvers.aod_parallel import AODParallelPlanner
from engine.targets import rectangle_target

STORE = Path(__file__).resolve().parent / "data" / "aod_parallel_plans.json"

#: (ny, nx, (r0, c0, height, width) of the target rectangle, loading, instances): centred, off-centre, full
#: height (planned transposed), full width, tall/narrow and short/wide targets on square and oblong arrays
CASES = (
    (16, 16, (4, 4, 8, 8), 0.6, 12),
    (24, 24, (0, 6, 24, 12), 0.6, 12),
    (24, 24, (6, 0, 12, 24), 0.6, 12),
    (24, 24, (2, 3, 20, 5), 0.55, 12),
    (24, 24, (10, 1, 4, 22), 0.5, 12),
    (32, 16, (8, 2, 16, 12), 0.6, 12),
    (16, 40, (3, 5, 10, 30), 0.6, 12),
    (64, 32, (16, 0, 32, 32), 0.6, 8),
    (70, 70, (15, 15, 40, 40), 0.6, 4),
)


def plan_digest(plan: Plan) -> str:
    """sha256 of everything a plan says: slot kinds, tone sites and deltas (unused tones are -1), and the steps."""
    ops = plan.operations
    n = ops.n
    h = hashlib.sha256()
    for part in (ops.kind[:n], ops.y_site[:n], ops.y_delta[:n], ops.x_site[:n], ops.x_delta[:n],
                 np.ascontiguousarray(plan.steps)):
        h.update(np.ascontiguousarray(part).tobytes())
    return h.hexdigest()


def plan_digests() -> dict[str, str]:
    """``{"ny x nx r0,c0,h,w eps objective #i": digest}`` over every case (``"unsolvable"`` when refused)."""
    out: dict[str, str] = {}
    for ny, nx, (r0, c0, hh, ww), eps, n in CASES:
        target = rectangle_target(nx=nx, ny=ny, row0=r0, col0=c0, rows=hh, cols=ww)
        for objective in ("slots", "transfers"):
            planner = AODParallelPlanner(nx, ny, objective=objective)
            for i in range(n):
                occ = np.random.default_rng(1000 + i).random((ny, nx)) < eps
                key = f"{ny}x{nx} {r0},{c0},{hh},{ww} {eps} {objective} #{i}"
                try:
                    planner.solve_moves(occ, target)
                except UnsolvableError:
                    out[key] = "unsolvable"
                    continue
                out[key] = plan_digest(planner.batch())
    return out


if __name__ == "__main__":
    STORE.parent.mkdir(exist_ok=True)
    STORE.write_text(json.dumps(plan_digests(), indent=1, sort_keys=True) + "\n")
    print(f"stored {STORE}", file=sys.stderr)
