"""Target patterns: which traps must hold an atom at the end of a shot (``bool[ny, nx]``)."""

from __future__ import annotations

from typing import Protocol

import numpy as np
from numba import njit

__all__ = ["TargetSpec", "build_target", "centre_target", "rectangle_target", "target_filled"]


class TargetSpec(Protocol):
    """What ``build_target`` reads from a target description: ``engine.config.TargetConfig`` is one.

    A protocol rather than the config model itself, so that the config (which checks its target with
    ``build_target``) imports this module and not the other way round."""

    @property
    def kind(self) -> str: ...
    @property
    def count(self) -> int | None: ...
    @property
    def row0(self) -> int: ...
    @property
    def col0(self) -> int: ...
    @property
    def rows(self) -> int | None: ...
    @property
    def cols(self) -> int | None: ...
    @property
    def mask(self) -> list[str] | None: ...


def centre_target(*, nx: int, ny: int, count: int) -> np.ndarray:
    """The paper's centre-compact target.

    A chain (``ny == 1``) gets ``count`` contiguous traps in the middle. A grid gets a full-width band of
    ``count / nx`` rows in the middle, reservoir rows above and below.
    """
    target = np.zeros((ny, nx), dtype=bool)
    if ny == 1:
        if not 1 <= count <= nx:
            raise ValueError(f"target.count must be between 1 and nx = {nx} for a chain (got {count})")
        start = (nx - count) // 2
        target[0, start : start + count] = True
        return target
    if count % nx:
        raise ValueError(
            f"target.count = {count} must be a multiple of nx = {nx} for a centre band on a grid "
            "(or use kind 'rectangle')"
        )
    rows = count // nx
    if not 1 <= rows <= ny:
        raise ValueError(f"target.count = {count} needs {rows} rows but the grid has ny = {ny}")
    start = (ny - rows) // 2
    target[start : start + rows, :] = True
    return target


def rectangle_target(*, nx: int, ny: int, row0: int, col0: int, rows: int, cols: int) -> np.ndarray:
    if row0 + rows > ny or col0 + cols > nx:
        raise ValueError(
            f"target rectangle rows {row0}..{row0 + rows - 1} x cols {col0}..{col0 + cols - 1} "
            f"does not fit the {ny}x{nx} array"
        )
    target = np.zeros((ny, nx), dtype=bool)
    target[row0 : row0 + rows, col0 : col0 + cols] = True
    return target


def _mask_target(*, nx: int, ny: int, mask: list[str]) -> np.ndarray:
    if len(mask) != ny:
        raise ValueError(f"target.mask has {len(mask)} rows but the array has ny = {ny}")
    target = np.zeros((ny, nx), dtype=bool)
    for r, line in enumerate(mask):
        if len(line) != nx or set(line) - {"0", "1"}:
            raise ValueError(f"target.mask row {r} must be {nx} characters of '0'/'1' (got {line!r})")
        target[r] = [ch == "1" for ch in line]
    return target


def build_target(cfg: TargetSpec, *, nx: int, ny: int) -> np.ndarray:
    """Build the configured target; raises ValueError naming what is wrong."""
    if cfg.kind == "centre":
        if cfg.count is None:
            raise ValueError("target.count is required for kind 'centre'")
        target = centre_target(nx=nx, ny=ny, count=cfg.count)
    elif cfg.kind == "rectangle":
        if cfg.rows is None or cfg.cols is None:
            raise ValueError("target.rows and target.cols are required for kind 'rectangle'")
        target = rectangle_target(nx=nx, ny=ny, row0=cfg.row0, col0=cfg.col0, rows=cfg.rows, cols=cfg.cols)
    else:
        if cfg.mask is None:
            raise ValueError("target.mask is required for kind 'mask'")
        target = _mask_target(nx=nx, ny=ny, mask=cfg.mask)
    if not target.any():
        raise ValueError("the target selects no trap")
    return target


@njit(cache=True, nogil=True)
def target_filled(occupancy: np.ndarray, target: np.ndarray) -> bool:
    """True when every target trap is occupied; a kernel, so the check in every cycle allocates nothing."""
    occ = occupancy.ravel()
    tgt = target.ravel()
    for i in range(tgt.size):
        if tgt[i] and not occ[i]:
            return False
    return True
