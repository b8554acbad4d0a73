"""Interstitial routing (``array.routing``): tweezers that travel between the traps, half a site off the lattice.

In the lattice model (``routing: lattice``) every tone of a slot starts and ends on a site, so a loaded tweezer
ends every slot over a trap and cannot pass an occupied one: a repair relays the atoms on its path. With
``routing: interstitial`` each AOD axis plays a comb of ``2 n - 1`` **positions**: position ``2 k`` is site
``k`` (its static tone) and position ``2 k + 1`` the point halfway between sites ``k`` and ``k + 1`` (the
frequency halfway between their tones). A tweezer at a position that is odd on either axis sits in a
**channel** between rows or columns of traps: no trap is below it, so an atom it carries collides with nothing
in the static traps, and an empty one captures nothing. A slot moves a tone by at most one position (half a
site), so a tone at a site steps into a channel and back, and a loaded tweezer passes occupied traps in a
channel. The same machinery then runs on the finer grid of positions: ``Operations`` (``half = 2``) list
positions, the waveform bank tabulates the position comb, the simulated AWG decodes positions, and the move
model and the world keep held atoms at positions, of which only the even/even ones are traps.

Position units: ``half`` positions per site (1 for lattice, 2 for interstitial); an axis of ``n`` sites has
``(n - 1) * half + 1`` positions. Occupancies, targets and camera images stay in traps.

Lattice plans still run under interstitial routing (a strategy's bulk planner plans on the lattice):
``lattice_to_positions`` splits every one-site shift into two half-site shifts with the same deltas. After the
first half every moving tweezer is in a channel, where nothing happens, so the plan does on the finer grid
exactly what it did on the lattice, in twice its shift slots.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from engine.operations import SHIFT
from engine.tones import Tones

__all__ = [
    "ROUTINGS", "lattice_to_positions", "n_positions", "position_name", "positions_of", "positions_per_site",
    "position_tones", "trap_index", "traps_of",
]  # fmt: skip

ROUTINGS = ("lattice", "interstitial")


def positions_per_site(routing: str) -> int:
    """1 for ``lattice``, 2 for ``interstitial`` (a position every half site)."""
    if routing not in ROUTINGS:
        raise ValueError(f"array.routing must be one of {', '.join(ROUTINGS)} (got {routing!r})")
    return 2 if routing == "interstitial" else 1


def n_positions(n_sites: int, half: int) -> int:
    """Positions of an axis of ``n_sites`` sites: the sites and, for ``half = 2``, the points between them."""
    return (n_sites - 1) * half + 1


def positions_of(occupancy: np.ndarray, half: int) -> np.ndarray:
    """``bool[ny, nx]`` traps as ``bool`` on the position grid (atoms at even/even positions, channels empty)."""
    occ = np.asarray(occupancy, dtype=bool)
    ny, nx = occ.shape
    out = np.zeros((n_positions(ny, half), n_positions(nx, half)), dtype=bool)
    out[::half, ::half] = occ
    return out


def traps_of(grid: np.ndarray, half: int) -> np.ndarray:
    """The traps of a position grid: a view of its even/even positions (the grid itself for ``half = 1``)."""
    return grid[::half, ::half]


def trap_index(flat: np.ndarray, nx: int, half: int) -> np.ndarray:
    """Flat position indices (on a grid of ``n_positions(nx, half)`` columns) that are traps -> flat trap indices
    (-1 stays -1: no atom)."""
    flat = np.asarray(flat, dtype=np.int64)
    px = n_positions(nx, half)
    return np.where(flat < 0, -1, (flat // px) // half * nx + (flat % px) // half)


def position_name(flat: int, n_cols: int, half: int) -> str:
    """``row r, col c`` of a flat position, in sites (``row 3.5`` is the channel between rows 3 and 4)."""
    r, c = divmod(int(flat), n_cols)
    return f"row {r / half:g}, col {c / half:g}"


def position_tones(tones: Tones, half: int) -> Tones:
    """The comb of positions: every site's tone and, for ``half = 2``, between sites ``k`` and ``k + 1`` the
    mean of their frequencies and amplitudes. Phases: a site keeps its own; a midpoint gets the phase that a
    tone moving there from site ``k`` with no correction would reach (``engine.waveforms.axes``'s continuous
    rule, which the site phases of a ``continuous`` comb follow too), so it is right for any comb, even or not.
    Whether the midpoints are whole cycles per slot is checked by the bank, which knows the slot."""
    if half == 1:
        return tones
    f, a, p = tones
    out_f = np.empty(2 * f.size - 1)
    out_a = np.empty_like(out_f)
    out_p = np.empty_like(out_f)
    out_f[::2], out_a[::2], out_p[::2] = f, a, p
    out_f[1::2] = (f[:-1] + f[1:]) / 2
    out_a[1::2] = (a[:-1] + a[1:]) / 2
    out_p[1::2] = p[:-1]  # the lower neighbour's; ``engine.waveforms.axes`` applies the rule above
    return Tones(out_f, out_a, out_p)


@njit(cache=True, nogil=True)
def lattice_to_positions(
    kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray, n: int,
    steps: np.ndarray, n_steps: int, nx: int,
    out_kind: np.ndarray, out_y_site: np.ndarray, out_y_delta: np.ndarray, out_x_site: np.ndarray,
    out_x_delta: np.ndarray, out_steps: np.ndarray,
) -> int:  # fmt: skip
    """A lattice plan (``n`` slots, ``n_steps`` one-site steps) written on the position grid (``half = 2``):
    sites doubled, every ``SHIFT`` twice (the tones move half a site in each), every step ``a -> b`` as
    ``a -> midpoint -> b``. The ``out_*`` tables must be cleared (-1 / 0) and large enough; returns the slots
    written (the steps written are ``2 * n_steps``)."""
    px = 2 * nx - 1
    m = 0
    for i in range(n):
        reps = 2 if kind[i] == SHIFT else 1
        for h in range(reps):
            out_kind[m] = kind[i]
            for t in range(y_site.shape[1]):
                if y_site[i, t] < 0:
                    break
                out_y_site[m, t] = y_site[i, t] * 2 + y_delta[i, t] * h
                out_y_delta[m, t] = y_delta[i, t]
            for t in range(x_site.shape[1]):
                if x_site[i, t] < 0:
                    break
                out_x_site[m, t] = x_site[i, t] * 2 + x_delta[i, t] * h
                out_x_delta[m, t] = x_delta[i, t]
            m += 1
    for k in range(n_steps):
        a, b = steps[k, 0], steps[k, 1]
        pa = (a // nx) * 2 * px + (a % nx) * 2
        pb = (b // nx) * 2 * px + (b % nx) * 2
        mid = (pa + pb) // 2
        out_steps[2 * k, 0] = pa
        out_steps[2 * k, 1] = mid
        out_steps[2 * k + 1, 0] = mid
        out_steps[2 * k + 1, 1] = pb
    return m
