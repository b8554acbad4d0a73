"""The simulated lab's ground truth: which traps hold atoms, and what the AOD tones do to them.

Two kinds of trap, following ``array.trap_source``:

- ``slm``: static traps on an ``ny x nx`` grid (from an SLM) plus mobile tweezers at every intersection of
  the y tracks x the x tracks of a slot, loaded or not. Tweezer depth is ``amp_x * amp_y``. Any tweezer at
  full depth over an occupied trap takes its atom (a transfer): when it ramps up there (an extract) or when
  it arrives there already at full depth (a capture; it then drags the atom along). A loaded tweezer carries
  its atom (one step per slot in which it moves) and implants it where its depth falls (one transfer); a
  loaded tweezer meeting an atom, by moving onto it or implanting onto it, is a light-assisted collision (both
  lost). A loaded tweezer that is simply gone at the start of a slot drops its atom.
- ``aod``: a 1D chain whose traps are the x tones themselves. An atom follows its tone's track (a step when it
  moves); a tone that fades out while holding an atom loses it, and an atom where no tone starts is lost.

These rules are ``engine/move_model.py``, the code the plan validator replays plans with.

Loss: ``survival_transfer`` per extract/implant, ``survival_step`` per one-site move, and vacuum lifetime
``exp(-dt / tau)`` per atom over clock time (``elapse_to``). ``lossless`` turns all of it off (collisions
and dropped atoms still lose atoms: they are mistakes, not noise). Counters record every cause.

Speed: a grid shot applies ~500 slots and as many vacuum steps, so each is one numba kernel call over the
world's own arrays (``mm.tweezer_slot``, ``mm.chain_slot``, ``_vacuum``) instead of a dozen small numpy ops. The
plain-numpy versions stay as the reference (``World(reference=True)``) and a test holds the two equal. Random
draws come from ``_Uniforms``, a buffer filled from ``rng`` in order: handing a ``Generator`` to a numba
function costs ~20 us per call (more than the slot itself), and since every draw the world makes is a uniform
double consumed in a fixed order, reading them from a pre-drawn buffer yields exactly the values the direct
``rng.random(n)`` calls would (same seed, same atoms lost; ``rng`` only runs ahead of what is consumed).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

from drivers.sim.decode import FULL_FRACTION, DecodedSegment
from engine import move_model as mm
from engine.config import SystemConfig
from engine.devices import Clock
from engine.move_model import MoveState

__all__ = ["World", "WorldCounters"]


@dataclass
class WorldCounters:
    """Events since the last ``reset``; ``lost_*`` count atoms."""

    loaded: int = 0
    transfers: int = 0
    steps: int = 0
    slots: int = 0
    lost_transfer: int = 0
    lost_step: int = 0
    lost_vacuum: int = 0
    lost_collision: int = 0
    lost_dropped: int = 0
    lost_released: int = 0
    captured: int = 0  # atoms an empty full-depth tweezer took on arriving over them (not by ramping up)
    dragged: int = 0  # captured atoms that then moved with their tweezer

    @property
    def lost(self) -> int:
        return (
            self.lost_transfer
            + self.lost_step
            + self.lost_vacuum
            + self.lost_collision
            + self.lost_dropped
            + self.lost_released
        )

    def as_dict(self) -> dict[str, int]:
        return {**asdict(self), "lost": self.lost}


class _Uniforms:
    """Uniform doubles drawn from ``rng`` ahead of use and handed out strictly in order.

    ``Generator.random(n)`` is ``n`` successive ``next_double`` calls, so any sequence of ``take(n_i)`` (or a
    kernel reading ``buf[pos:pos + k]``) sees exactly the numbers the same sequence of ``rng.random(n_i)``
    calls would have returned. This is what lets the numba kernels draw without being handed the
    ``Generator`` (whose unboxing costs more than a slot's work).
    """

    CHUNK = 1 << 14

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.buf = np.empty(0, dtype=np.float64)
        self.pos = 0

    def ensure(self, n: int) -> None:
        """Make at least ``n`` unread numbers available from ``pos`` (unread ones move to the front first)."""
        left = self.buf.size - self.pos
        if left >= n:
            return
        size = max(self.buf.size, self.CHUNK, 2 * n)
        if size != self.buf.size:
            buf = np.empty(size, dtype=np.float64)
            buf[:left] = self.buf[self.pos :]
            self.buf = buf
        else:
            self.buf[:left] = self.buf[self.pos :].copy()
        self.rng.random(out=self.buf[left:])
        self.pos = 0

    def take(self, n: int) -> np.ndarray:
        """The next ``n`` numbers (a view, valid until the next ``ensure``)."""
        self.ensure(n)
        out = self.buf[self.pos : self.pos + n]
        self.pos += n
        return out


class World:
    """Atoms in static traps and in mobile tweezers; seeded, so a shot replays exactly.

    ``reference=True`` runs the plain-numpy slot and vacuum code instead of the numba kernels (same results,
    same random numbers; kept to test the kernels against).
    """

    def __init__(
        self,
        config: SystemConfig,
        *,
        clock: Clock | None = None,
        rng: np.random.Generator | None = None,
        lossless: bool | None = None,
        reference: bool = False,
    ) -> None:
        self.clock = clock
        self.rng = rng if rng is not None else np.random.default_rng(config.sim.seed)
        self.counters = WorldCounters()
        self.reference = reference
        self.nx = self.ny = 0
        self.reconfigure(config, lossless=lossless)
        self._t_s = clock.now_s() if clock is not None else 0.0
        _warm_up()

    @property
    def rng(self) -> np.random.Generator:
        return self._uniforms.rng

    @rng.setter
    def rng(self, rng: np.random.Generator) -> None:
        """A new generator drops the numbers pre-drawn from the old one."""
        self._uniforms = _Uniforms(rng)

    def reconfigure(self, config: SystemConfig, *, lossless: bool | None = None) -> None:
        """Adopt the array and loss model of ``config``; a new array size starts empty (between shots only)."""
        arr = config.array
        self.trap_source = arr.trap_source
        sim = config.sim
        self.loading_probability = sim.loading_probability
        self.survival_transfer = sim.survival_transfer
        self.survival_step = sim.survival_step
        self.vacuum_lifetime_s = sim.vacuum_lifetime_s
        self.lossless = sim.lossless if lossless is None else lossless
        if (arr.ny, arr.nx) != (self.ny, self.nx):
            self.nx, self.ny = arr.nx, arr.ny
            self._static = np.zeros((self.ny, self.nx), dtype=bool)
            self._held = np.zeros((self.ny, self.nx), dtype=bool)  # atoms in tweezers, at the tweezer's site
            self._move = MoveState(self.ny, self.nx)  # the move model's scratch (and how held atoms were taken)
            self._move_events = mm.new_events()

    # --- state -----------------------------------------------------------------------------------------

    def load(self) -> np.ndarray:
        """Empty every trap and tweezer, then fill each trap with probability ``loading_probability``."""
        self._static[:] = self._uniforms.take(self.ny * self.nx).reshape(self.ny, self.nx) < self.loading_probability
        self._held[:] = False
        self.counters.loaded += int(self._static.sum())
        self._t_s = self._now()
        return self.occupancy()

    def set_occupancy(self, occupancy: np.ndarray) -> None:
        """Place atoms by hand (tests, scripted scenarios); empties the tweezers."""
        occ = np.asarray(occupancy, dtype=bool).reshape(self.ny, self.nx)
        self._static[:] = occ
        self._held[:] = False
        self._t_s = self._now()

    def occupancy(self) -> np.ndarray:
        """Static-trap ground truth now (what a camera would image): read-only ``bool[ny, nx]``."""
        if self.clock is not None:
            self.elapse_to(self.clock.now_s())
        view = self._static.view()
        view.flags.writeable = False
        return view

    def held(self) -> np.ndarray:
        """Atoms in mobile tweezers, at their tweezer's site: read-only ``bool[ny, nx]`` (slm only)."""
        view = self._held.view()
        view.flags.writeable = False
        return view

    @property
    def n_atoms(self) -> int:
        return int(self._static.sum() + self._held.sum())

    # --- time ------------------------------------------------------------------------------------------

    def _now(self) -> float:
        return self.clock.now_s() if self.clock is not None else self._t_s

    def elapse_to(self, t_s: float) -> None:
        """Apply vacuum loss for the time since the world was last brought up to date (never backwards)."""
        dt = t_s - self._t_s
        if dt <= 0:
            return
        self._t_s = t_s
        if self.lossless:
            return
        p_keep = float(np.exp(-dt / self.vacuum_lifetime_s))
        if self.reference:
            self._vacuum_reference(p_keep)
            return
        u = self._uniforms
        need = self._static.size + self._held.size
        if u.buf.size - u.pos < need:
            u.ensure(need)
        u.pos, lost = _vacuum(self._static, self._held, u.buf, u.pos, p_keep)
        self.counters.lost_vacuum += lost

    def _vacuum_reference(self, p_keep: float) -> None:
        for grid in (self._static, self._held):
            idx = np.flatnonzero(grid)
            if idx.size:
                gone = idx[self._uniforms.take(idx.size) >= p_keep]
                grid.flat[gone] = False
                self.counters.lost_vacuum += int(gone.size)

    # --- slots -----------------------------------------------------------------------------------------

    def apply_slot(self, x_tracks: np.ndarray, y_tracks: np.ndarray | None) -> None:
        """Apply one decoded slot: ``*_tracks`` are ``[m, 4]`` rows ``(site0, site1, amp0, amp1)``.

        The rules are the move model's (``engine/move_model.py``), the same code the plan validator replays
        plans with; here the losses are drawn from the world's random numbers.
        """
        self.counters.slots += 1
        events = self._move_events
        events[:] = 0  # (the world does not use the first-fault sites the validator reads)
        if self.trap_source == "aod":
            self._apply_chain(np.ascontiguousarray(x_tracks, dtype=np.float32), events)
        else:
            yt = y_tracks if y_tracks is not None else _NO_TRACKS
            self._apply_tweezers(
                np.ascontiguousarray(x_tracks, dtype=np.float32), np.ascontiguousarray(yt, dtype=np.float32), events
            )
        e = events.tolist()  # Python ints: cheaper to add than numpy scalars, ~500 slots a shot
        c = self.counters
        c.transfers += e[mm.EV_PICKED] + e[mm.EV_CAPTURED] + e[mm.EV_IMPLANTED]
        c.captured += e[mm.EV_CAPTURED]
        c.dragged += e[mm.EV_DRAGGED]
        c.steps += e[mm.EV_STEPS]
        c.lost_transfer += e[mm.EV_LOST_TRANSFER]
        c.lost_step += e[mm.EV_LOST_STEP]
        c.lost_collision += e[mm.EV_LOST_COLLISION]
        c.lost_dropped += e[mm.EV_LOST_DROPPED]
        c.lost_released += e[mm.EV_LOST_RELEASED]

    def _apply_chain(self, tracks: np.ndarray, events: np.ndarray) -> None:
        """The chain conveyor (``move_model.chain_slot``; ``reference``: ``chain_slot_reference``)."""
        atoms = self._static[0]
        if not atoms.any():
            return
        draw = not self.lossless and self.survival_step < 1.0
        u = self._uniforms
        if draw and u.buf.size - u.pos < self.nx:
            u.ensure(self.nx)
        if self.reference:
            u.pos = mm.chain_slot_reference(
                tracks, FULL_FRACTION, atoms, u.buf, u.pos, self.survival_step if draw else None, events
            )
            return
        st = self._move
        u.pos = mm.chain_slot(
            tracks, FULL_FRACTION, atoms, st.ids[0, 0], st.atom_stats, False, st.chain_scratch, u.buf, u.pos,
            draw, self.survival_step, events,
        )  # fmt: skip

    def _apply_tweezers(self, xt: np.ndarray, yt: np.ndarray, events: np.ndarray) -> None:
        """The product-set tweezers (``move_model.tweezer_slot``; ``reference``: ``tweezer_slot_reference``)."""
        st = self._move
        n_tweezers = xt.shape[0] * yt.shape[0]
        if st.tweezers.shape[0] < n_tweezers:  # more tracks than sites: grow the scratch once
            st.tweezers = np.zeros((n_tweezers, 8), dtype=np.int64)
        draw_transfer = not self.lossless and self.survival_transfer < 1.0
        draw_step = not self.lossless and self.survival_step < 1.0
        u = self._uniforms
        need = 2 * n_tweezers  # at most one step and one transfer per tweezer
        if (draw_transfer or draw_step) and u.buf.size - u.pos < need:
            u.ensure(need)
        if self.reference:
            u.pos = mm.tweezer_slot_reference(
                yt, xt, FULL_FRACTION, self._static, self._held, st.held_mark, u.buf, u.pos,
                self.survival_transfer if draw_transfer else None, self.survival_step if draw_step else None, events,
            )  # fmt: skip
            return
        u.pos = mm.tweezer_slot(
            yt, xt, FULL_FRACTION, self._static, self._held, st.held_mark, st.ids, st.atom_stats, False, st.arrivals,
            st.tweezers, u.buf, u.pos,
            draw_transfer, self.survival_transfer, draw_step, self.survival_step, events,
        )  # fmt: skip

    def apply_segment(self, decoded: DecodedSegment, t0_s: float | None = None, slot_s: float = 0.0) -> None:
        """Apply every slot of a decoded segment (vacuum loss up to each slot's start when ``t0_s`` is given)."""
        for i in range(decoded.n_slots):
            if t0_s is not None:
                self.elapse_to(t0_s + i * slot_s)
            self.apply_slot(*decoded.slot(i))


_NO_TRACKS = np.zeros((0, 4), dtype=np.float32)


# --- kernels ---------------------------------------------------------------------------------------------
# Each one replays its ``World._*_reference`` method step for step: the same conditions evaluated on the same
# state (all of a stage's reads before its writes, as the vectorised code does), and the same uniforms read
# from ``u`` in the same order (the order of ``np.flatnonzero`` over the same masks).


@njit(cache=True, nogil=True)
def _vacuum(static: np.ndarray, held: np.ndarray, u: np.ndarray, pos: int, p_keep: float) -> tuple[int, int]:
    """Vacuum loss: one uniform per atom, static traps first then tweezers, row-major. Returns (pos, lost)."""
    lost = 0
    for grid in (static, held):
        flat = grid.reshape(grid.size)
        for i in range(flat.size):
            if flat[i]:
                if u[pos] >= p_keep:
                    flat[i] = False
                    lost += 1
                pos += 1
    return pos, lost


def _warm_up() -> None:
    """Compile (or load from the cache) every kernel now, not during the first shot; no state is touched."""
    if _warm_up.done:  # type: ignore[attr-defined]
        return
    grid = np.zeros((1, 1), dtype=bool)
    u = np.zeros(4)
    one = np.array([[0, 0, 1, 1]], dtype=np.float32)
    _vacuum(grid, grid.copy(), u, 0, 1.0)
    st = MoveState(1, 1)
    ev = mm.new_events()
    mm.tweezer_slot(
        one, one, 0.5, st.static, st.held, st.held_mark, st.ids, st.atom_stats, False, st.arrivals, st.tweezers, u, 0,
        False, 1.0, False, 1.0, ev,
    )  # fmt: skip
    mm.chain_slot(one, 0.5, st.static[0], st.ids[0, 0], st.atom_stats, False, st.chain_scratch, u, 0, False, 1.0, ev)
    _warm_up.done = True  # type: ignore[attr-defined]


_warm_up.done = False  # type: ignore[attr-defined]
