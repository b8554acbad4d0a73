"""The AOD-parallel planner's records and the primitives every phase shares (see ``aod_parallel``).

Everything works in an *internal frame*: ``g[c, r]`` is the occupancy of internal column ``c`` (the unit that
the vertical phase compresses) at internal row ``r``. Without transposition internal rows/columns are the
array's rows/columns; transposed they are its columns/rows (the target rectangle spans every row, so its
columns become full-width rows). The target is the rectangle ``rows r0..r1-1 x columns c0..c1-1``.

Plans are recorded as *batches*, each one EXTRACT, ``n_shift`` SHIFT slots and one IMPLANT, on a product
set of row tones x column tones. Every tone has a direction (-1, 0, +1) and a number of slots it moves
(moving first, then waiting), so a batch record is enough to write the slots and to replay them:

``bmeta[b] = (row0, row1, col0, col1, n_shift, kind)``: the batch's row tones are
``brow[row0:row1]`` (ascending, internal rows) with directions ``brs`` and move counts ``brm``, its column tones
``bcol[col0:col1]`` with ``bcs`` and ``bcm``. ``kind``: 0 fill, 1 horizontal hop, 2 column compression.
Every phase appends batches and one-site ``steps`` and passes the counts on (``nb`` batches, ``nrr`` row
tones, ``ncr`` column tones, ``n_steps``).
"""

from __future__ import annotations

import numpy as np
from llvmlite import ir
from numba import config as numba_config
from numba import njit, types
from numba.extending import intrinsic

OK = 0
UNSOLVABLE = 1
OVERFLOW = 2  # a record buffer is too small (the planner grows it and plans again)
STUCK = 3  # balancing found no legal hop (not seen on random fillings; reported, never silently wrong)

K_FILL = 0
K_HOP = 1
K_COLUMN = 2


if numba_config.DISABLE_JIT:  # type: ignore[attr-defined]  # numba sets it at import; its stubs omit it
    # the kernels run as plain Python (the reference the tests compare against)

    def _popcount(x: np.uint64) -> int:
        return bin(int(x)).count("1")

    def _lowbit_index(x: np.uint64) -> int:
        word = int(x)
        return (word & -word).bit_length() - 1

else:

    @intrinsic
    def _ctpop(typingctx, x):  # noqa: ANN001, ANN202 - one popcnt instruction
        sig = types.uint64(types.uint64)

        def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
            return builder.ctpop(args[0])

        return sig, codegen

    @intrinsic
    def _cttz(typingctx, x):  # noqa: ANN001, ANN202 - count trailing zeros of a non-zero word
        sig = types.uint64(types.uint64)

        def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202
            return builder.cttz(args[0], ir.Constant(ir.IntType(1), 1))

        return sig, codegen

    @njit(cache=True, nogil=True, inline="always")
    def _popcount(x: np.uint64) -> int:
        return int(_ctpop(x))  # type: ignore[call-arg]  # numba's stubs type an @intrinsic call as its typing hook

    @njit(cache=True, nogil=True, inline="always")
    def _lowbit_index(x: np.uint64) -> int:
        """Index of the lowest set bit of a non-zero word."""
        return int(_cttz(x))  # type: ignore[call-arg]  # numba's stubs type an @intrinsic call as its typing hook


@njit(cache=True, nogil=True, inline="always")
def _flat(c: int, r: int, transposed: bool, nx_real: int) -> int:
    if transposed:
        return c * nx_real + r
    return r * nx_real + c


@njit(cache=True, nogil=True, inline="always")
def _put_tone(site: np.ndarray, sign: np.ndarray, moves: np.ndarray, n: int, at: int, sg: int, m: int) -> int:
    """Append a tone to a batch's row (or column) list: start site, direction (-1, 0, +1), sites travelled.
    Returns the new length of the list."""
    site[n] = at
    sign[n] = sg
    moves[n] = m
    return n + 1


@njit(cache=True, nogil=True, inline="always")
def _close_batch(bmeta: np.ndarray, nb: int, r0: int, r1: int, c0: int, c1: int, travel: int, kind: int) -> None:
    """Record batch ``nb``: row tones ``[r0, r1)``, column tones ``[c0, c1)``, the longest travel, its kind."""
    bmeta[nb, 0] = r0
    bmeta[nb, 1] = r1
    bmeta[nb, 2] = c0
    bmeta[nb, 3] = c1
    bmeta[nb, 4] = travel
    bmeta[nb, 5] = kind
