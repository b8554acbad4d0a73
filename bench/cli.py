"""The ``llrs bench`` subcommands: one per benchmark module, each registering its own arguments."""

from __future__ import annotations

import argparse

from bench import (
    assembly,
    assembly_bound,
    chain_plan,
    imaging,
    jitter,
    load,
    redrec,
    runtime,
    soak,
    solvers,
    streaming,
)

__all__ = ["register"]


def register(bench_sub: argparse._SubParsersAction) -> None:
    """Add every benchmark's subcommand to ``llrs bench``."""
    every = (runtime, load, soak, solvers, assembly, assembly_bound, chain_plan, imaging, redrec, streaming, jitter)
    for module in every:
        module.register(bench_sub)
