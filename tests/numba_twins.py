"""Run a script twice, compiled by numba and as plain Python (``NUMBA_DISABLE_JIT=1``), for the tests that
check a planner's kernels against their own source: the plain-Python run is the readable reference."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

from engine.operations import Plan

REPO = Path(__file__).resolve().parents[1]


def jit_and_python_outputs(script: str) -> tuple[Any, Any]:
    """The JSON ``script`` prints, compiled and then interpreted."""
    runs = []
    for disable in ("0", "1"):
        env = {**os.environ, "NUMBA_DISABLE_JIT": disable, "PYTHONPATH": str(REPO)}
        res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, cwd=REPO,
                             check=True)
        runs.append(json.loads(res.stdout))
    return runs[0], runs[1]


#: What every plan-twin script starts with: ``np``, ``plan_summary`` and the list ``out`` it appends to.
_PLANS_PRELUDE = "import json\nimport numpy as np\nfrom tests.numba_twins import plan_summary\nout = []\n"


def assert_plans_agree(body: str, *, at_least: int) -> None:
    """Run ``body`` (it appends ``plan_summary(plan)`` of each plan it makes to ``out``) compiled and as plain
    Python: the same plans, and at least ``at_least`` of them (so a script that plans nothing fails)."""
    compiled, interpreted = jit_and_python_outputs(_PLANS_PRELUDE + body + "print(json.dumps(out))\n")
    assert compiled == interpreted, "the compiled kernels and their plain-Python run made different plans"
    assert len(compiled) >= at_least, f"{len(compiled)} plans compared, expected at least {at_least}"


def plan_summary(plan: Plan) -> list[Any]:
    """What the twin scripts compare of a plan, as JSON: its steps and every slot described."""
    ops = plan.operations
    return [plan.steps.tolist(), [ops.describe(i) for i in range(len(ops))]]
