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

Loss: ``survival_transfer`` per extract/implant, ``survival_step`` per one-site move (times the speed
model's survival for the slot's duration and shape when ``sim.moves.site_spacing_um`` is set), and vacuum loss
with lifetime ``vacuum_lifetime_s``. ``lossless`` turns all of it off (collisions and dropped atoms still lose atoms:
they are mistakes, not noise). Counters record every cause.

Vacuum loss as background-gas hits: every site (each static trap and each tweezer position) is hit at the
times of its own Poisson process of rate ``1 / vacuum_lifetime_s``, and an atom is lost at the first hit on the
site it occupies. Since at most one atom sits on a site and hits on different sites are independent, each
atom's survival over a time ``dt`` is ``exp(-dt / tau)`` however it moves: its lifetime is exponential with
mean ``tau``. The hit times are drawn ahead (the next one per site) and consumed in time order, so which atoms
are lost depends only on where the atoms are when, never on how often ``elapse_to`` is called. (A death time
drawn per atom at loading would do the same, but it would have to travel with the atom through every slot
kernel; the hits stay with the sites, and the slot code only moves booleans.)

Replay: each kind of event draws from its own random stream (loading from the ``rng`` handed in; moves and
vacuum hits from two children spawned from it), so a change in one (say, a plan with more transfers) leaves
the others' numbers untouched, and the same seed gives the same atoms, shot for shot, whatever the timing of
the calls.

Speed: a grid shot applies ~500 slots and as many vacuum updates, so each is one numba kernel call over the
world's own arrays (``mm.tweezer_slot``, ``mm.chain_slot``, ``_vacuum``) instead of a dozen small numpy ops. The
plain-numpy versions stay as the reference (``World(reference=True)``) and a test holds the two equal. Random
draws come from ``_Uniforms``, a buffer per stream filled from its generator in order: handing a ``Generator``
to a numba function costs ~20 us per call (more than the slot itself), and since every draw the world makes is
a uniform double consumed in a fixed order, reading them from a pre-drawn buffer yields exactly the values the
direct ``rng.random(n)`` calls would (the generator only runs ahead of what is consumed).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from numba import njit

from drivers.sim.decode import FULL_FRACTION, DecodedSegment
from drivers.sim.move_loss import move_survival, trap_parameters
from engine import move_model as mm
from engine.config import SystemConfig
from engine.devices import Clock
from engine.move_model import MoveState
from engine.routing import n_positions, positions_per_site, traps_of

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
    lost_imaging: int = 0
    lost_trap: int = 0  # atoms a lossy trap lost (the ``set_trap_survival`` test hook)
    lost_pass_by: int = 0  # interstitial routing: atoms in traps a loaded tweezer passed half a site away
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
            + self.lost_imaging
            + self.lost_trap
            + self.lost_pass_by
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

    ``rng`` seeds every random stream of the world (loading draws from it directly, moves and vacuum hits from
    children spawned from it). ``reference=True`` runs the plain-numpy slot and vacuum code instead of the
    numba kernels (same results, same random numbers; kept to test the kernels against).
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
        self.reseed(rng if rng is not None else np.random.default_rng(config.sim.seed))
        self.counters = WorldCounters()
        self.reference = reference
        self.nx = self.ny = self._grid_half = 0
        self.vacuum_lifetime_s = 0.0
        self.lossless = True
        self._t_s = clock.now_s() if clock is not None else 0.0
        self._first_hit_s = np.inf  # no hit process yet: ``reconfigure`` starts one
        self._trap_survival: np.ndarray | None = None  # see set_trap_survival
        self._trap_loss_rng = np.random.default_rng(0)
        self.reconfigure(config, lossless=lossless)
        _warm_up()

    def reseed(self, rng: np.random.Generator) -> None:
        """Start every random stream afresh from ``rng``: loading draws from it, and moves, vacuum hits and
        imaging from children spawned from it, so each kind of event has a stream of its own."""
        move_rng, vacuum_rng, imaging_rng = rng.spawn(3)
        self._load_draws = _Uniforms(rng)
        self._move_draws = _Uniforms(move_rng)  # transfers and steps, in the order the slots need them
        self._vacuum_draws = _Uniforms(vacuum_rng)  # waiting times between background-gas hits
        self._imaging_rng = imaging_rng  # which imaged atoms are heated out, and when
        if getattr(self, "nx", 0):  # already configured: the hits drawn ahead came from the old stream
            self._draw_first_hits()

    def reconfigure(self, config: SystemConfig, *, lossless: bool | None = None) -> None:
        """Adopt the array and loss model of ``config``; a new array size starts empty (between shots only)."""
        self.elapse_to(self._now())  # hits so far follow the old loss model
        arr = config.array
        self.trap_source = arr.trap_source
        sim = config.sim
        self.loading_probability = sim.loading_probability
        self.survival_transfer = sim.survival_transfer
        self.survival_step = sim.survival_step
        if sim.moves.site_spacing_um is not None:  # speed costs atoms: see drivers/sim/move_loss.py
            wf = config.waveforms
            p_transfer, p_step = move_survival(
                wf.slot_duration_s, wf.shape, wf.shape_sharpness, sim.moves.site_spacing_um, trap_parameters(sim.moves)
            )
            self.survival_transfer *= p_transfer
            self.survival_step *= p_step
        # interstitial routing: a slot moves a tweezer half a site; its atom survives a half-site move with
        # sqrt(survival_step), so a path risks the same per site however it is cut into slots
        self.half = positions_per_site(arr.routing)
        self.survival_tweezer_step = self.survival_step ** (1.0 / self.half)
        self.pass_by_survival = sim.moves.pass_by_survival
        lossless = sim.lossless if lossless is None else lossless
        vacuum_changed = (sim.vacuum_lifetime_s, lossless) != (self.vacuum_lifetime_s, self.lossless)
        self.vacuum_lifetime_s = sim.vacuum_lifetime_s
        self.lossless = lossless
        self._configure_imaging(config)
        if (arr.ny, arr.nx, self.half) != (self.ny, self.nx, self._grid_half):
            self.nx, self.ny, self._grid_half = arr.nx, arr.ny, self.half
            py, px = n_positions(self.ny, self.half), n_positions(self.nx, self.half)
            # static atoms on the grid of positions (engine/routing.py; channels never hold one) and its traps
            self._grid = np.zeros((py, px), dtype=bool)
            self._static = traps_of(self._grid, self.half)
            self._held = np.zeros((py, px), dtype=bool)  # atoms in tweezers, at the tweezer's position
            self._move = MoveState(py, px)  # the move model's scratch (and how held atoms were taken)
            self._move_events = mm.new_events()
            vacuum_changed = True
        if vacuum_changed:
            self._draw_first_hits()

    # --- state -----------------------------------------------------------------------------------------

    def load(self) -> np.ndarray:
        """Empty every trap and tweezer, then fill each trap with probability ``loading_probability``."""
        self.elapse_to(self._now())  # hits up to now strike the old atoms, not the fresh ones
        self._static[:] = self._load_draws.take(self.ny * self.nx).reshape(self.ny, self.nx) < self.loading_probability
        self._held[:] = False
        self.counters.loaded += int(self._static.sum())
        return self.occupancy()

    def set_occupancy(self, occupancy: np.ndarray) -> None:
        """Place atoms by hand (tests, scripted scenarios); empties the tweezers."""
        occ = np.asarray(occupancy, dtype=bool).reshape(self.ny, self.nx)
        self.elapse_to(self._now())
        self._static[:] = occ
        self._held[:] = False

    def occupancy(self) -> np.ndarray:
        """Static-trap ground truth now (what a camera would image): read-only ``bool[ny, nx]``."""
        if self.clock is not None:
            self.elapse_to(self.clock.now_s())
        view = self._static.view()
        view.flags.writeable = False
        return view

    def held(self) -> np.ndarray:
        """Atoms in mobile tweezers, at their tweezer's position: read-only ``bool`` on the grid of positions
        (``engine.routing``: ``[ny, nx]`` under lattice routing; slm only)."""
        view = self._held.view()
        view.flags.writeable = False
        return view

    @property
    def n_atoms(self) -> int:
        return int(self._static.sum() + self._held.sum())

    # --- time ------------------------------------------------------------------------------------------

    def _now(self) -> float:
        return self.clock.now_s() if self.clock is not None else self._t_s

    def _draw_first_hits(self) -> None:
        """Start every site's background-gas process afresh at the world's time (memoryless, so no bias).

        ``_next_hit_s[0]`` are the static traps, ``[1]`` the tweezer sites; infinite when lossless.
        """
        self._next_hit_s = np.full((2, *self._grid.shape), np.inf)
        if not self.lossless:
            waits = self._vacuum_draws.take(self._next_hit_s.size).reshape(self._next_hit_s.shape)
            self._next_hit_s[:] = self._t_s - self.vacuum_lifetime_s * np.log1p(-waits)
        self._first_hit_s = float(self._next_hit_s.min())

    def elapse_to(self, t_s: float) -> None:
        """Apply the vacuum hits since the world was last brought up to date (never backwards).

        Call it before atoms move: a hit strikes whatever sits on its site when the world learns of it.
        """
        if t_s <= self._t_s:
            return
        self._t_s = t_s
        if t_s < self._first_hit_s:  # nearly every call: no site is hit before t_s
            return
        if self.reference:
            self._vacuum_reference(t_s)
            return
        u = self._vacuum_draws
        done = False
        while not done:
            u.ensure(64)
            u.pos, lost, done = _vacuum(
                self._grid, self._held, self._next_hit_s, t_s, u.buf, u.pos, self.vacuum_lifetime_s
            )
            self.counters.lost_vacuum += lost
        self._first_hit_s = float(self._next_hit_s.min())

    def _vacuum_reference(self, t_s: float) -> None:
        hits = self._next_hit_s.reshape(2, -1)
        grids = (self._grid.reshape(-1), self._held.reshape(-1))
        while True:
            kind, site = np.unravel_index(np.argmin(hits), hits.shape)
            if hits[kind, site] > t_s:
                break
            if grids[kind][site]:
                grids[kind][site] = False
                self.counters.lost_vacuum += 1
            hits[kind, site] -= self.vacuum_lifetime_s * np.log1p(-self._vacuum_draws.take(1)[0])
        self._first_hit_s = float(hits.min())

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
            xt = np.ascontiguousarray(x_tracks, dtype=np.float32)
            yt = np.ascontiguousarray(yt, dtype=np.float32)
            self._apply_tweezers(xt, yt, events)
            if self.half > 1 and self.pass_by_survival < 1.0 and not self.lossless:
                self._pass_by(xt, yt)
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
        if self._trap_survival is not None:
            self._lossy_traps()

    # --- test hook: traps that lose atoms (a bad spot of the trap light, a lossy AOD column) -------------

    def set_trap_survival(self, survival: np.ndarray | None, *, seed: int = 0) -> None:
        """Make some static traps lossy: ``survival`` (``float[ny, nx]``, each in [0, 1]) is the probability
        that an atom sitting in a trap outlives one waveform slot there; ``None`` makes every trap perfect again.

        For diagnostics: a trap made lossy on purpose must stand out in the per-trap survival statistics. Its
        random numbers are a stream of their own (from ``seed``), so the world's other streams are unchanged.
        """
        if survival is None:
            self._trap_survival = None
            return
        p = np.asarray(survival, dtype=np.float64)
        if p.shape != (self.ny, self.nx) or not np.all((p >= 0.0) & (p <= 1.0)):
            raise ValueError(f"trap survival must be float[{self.ny}, {self.nx}] with values in [0, 1]")
        self._trap_survival = p.copy()
        self._trap_loss_rng = np.random.default_rng(seed)

    def _lossy_traps(self) -> None:
        assert self._trap_survival is not None
        if self._trap_survival.shape != self._static.shape:  # the array changed size: the hook no longer applies
            self._trap_survival = None
            return
        lost = self._static & (self._trap_loss_rng.random(self._static.shape) >= self._trap_survival)
        self._static &= ~lost
        self.counters.lost_trap += int(lost.sum())

    def _apply_chain(self, tracks: np.ndarray, events: np.ndarray) -> None:
        """The chain conveyor (``move_model.chain_slot``; ``reference``: ``chain_slot_reference``)."""
        atoms = self._static[0]
        if not atoms.any():
            return
        draw = not self.lossless and self.survival_step < 1.0
        u = self._move_draws
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
        u = self._move_draws
        need = 2 * n_tweezers  # at most one step and one transfer per tweezer
        if (draw_transfer or draw_step) and u.buf.size - u.pos < need:
            u.ensure(need)
        if self.reference:
            u.pos = mm.tweezer_slot_reference(
                yt, xt, FULL_FRACTION, self.half, self._grid, self._held, st.held_mark, u.buf, u.pos,
                self.survival_transfer if draw_transfer else None, self.survival_tweezer_step if draw_step else None,
                events,
            )  # fmt: skip
            return
        u.pos = mm.tweezer_slot(
            yt, xt, FULL_FRACTION, self.half, self._grid, self._held, st.held_mark, st.ids, st.atom_stats, False,
            st.arrivals, st.tweezers, u.buf, u.pos,
            draw_transfer, self.survival_transfer, draw_step, self.survival_tweezer_step, events,
        )  # fmt: skip

    def _pass_by(self, xt: np.ndarray, yt: np.ndarray) -> None:
        """``sim.moves.pass_by_survival``: every occupied trap half a site from a loaded tweezer that moved this
        slot (the two traps either side of its channel) keeps its atom with that probability, one draw per
        trap passed, from the move stream."""
        r, c = np.nonzero(self._held)
        if r.size == 0:
            return
        py, px = self._grid.shape
        row_moved = np.zeros(py, dtype=bool)  # a tone that ends the slot at this position moved in it
        col_moved = np.zeros(px, dtype=bool)
        row_moved[yt[:, 1].astype(np.int64)] = yt[:, 0] != yt[:, 1]
        col_moved[xt[:, 1].astype(np.int64)] = xt[:, 0] != xt[:, 1]
        moved = row_moved[r] | col_moved[c]
        r, c = r[moved], c[moved]
        row_channel = (r % 2 == 1) & (c % 2 == 0)  # between rows: traps above and below
        col_channel = (r % 2 == 0) & (c % 2 == 1)  # between columns: traps left and right
        rr = np.concatenate([r[row_channel] - 1, r[row_channel] + 1, r[col_channel], r[col_channel]])
        cc = np.concatenate([c[row_channel], c[row_channel], c[col_channel] - 1, c[col_channel] + 1])
        inside = (rr >= 0) & (rr < py) & (cc >= 0) & (cc < px)
        rr, cc = rr[inside], cc[inside]
        hit = self._grid[rr, cc]
        rr, cc = rr[hit], cc[hit]
        if rr.size == 0:
            return
        lost = self._move_draws.take(rr.size) >= self.pass_by_survival
        self._grid[rr[lost], cc[lost]] = False
        self.counters.lost_pass_by += int(lost.sum())

    def apply_segment(self, decoded: DecodedSegment, t0_s: float | None = None, slot_s: float = 0.0) -> None:
        """Apply every slot of a decoded segment (vacuum loss up to each slot's start when ``t0_s`` is given)."""
        for i in range(decoded.n_slots):
            if t0_s is not None:
                self.elapse_to(t0_s + i * slot_s)
            self.apply_slot(*decoded.slot(i))

    # --- imaging ---------------------------------------------------------------------------------------

    def _configure_imaging(self, config: SystemConfig) -> None:
        """Adopt ``sim.imaging``'s loss rate (the imaging stream is the world's own, see ``reseed``)."""
        self.imaging_loss_rate_hz = config.sim.imaging.loss_rate_hz

    def expose(self, t0_s: float, exposure_s: float) -> np.ndarray:
        """Image the static traps from ``t0_s`` for ``exposure_s``: returns ``float64[ny, nx]``, the fraction of
        the exposure each trap's atom was there (0: empty; 1: there throughout).

        Scattering the imaging light heats atoms out of their traps at ``loss_rate_hz`` while the light is
        on, so an atom survives the image with probability ``exp(-rate * exposure_s)`` (the imaging loss
        grows with the exposure, as the scattered photons do). A lost atom leaves at a time ``t`` drawn from
        the exponential law truncated to the exposure: with one uniform ``u`` per atom, the atom is lost when
        ``u < 1 - exp(-rate * exposure_s)`` and then ``t = -ln(1 - u) / rate`` (the inverse CDF), and it is
        bright for ``t / exposure_s`` of the image. Lost atoms leave the world at once (nothing moves atoms
        during an exposure); vacuum loss keeps running on the world's clock as before. ``lossless`` turns
        imaging loss off too.
        """
        if exposure_s <= 0:
            raise ValueError(f"exposure_s must be positive (got {exposure_s})")
        self.elapse_to(t0_s)
        present = self._static.astype(np.float64)
        rate_hz = self.imaging_loss_rate_hz
        if self.lossless or rate_hz == 0.0:
            return present
        atoms = np.flatnonzero(self._static)
        u = self._imaging_rng.random(atoms.size)
        lost = u < -np.expm1(-rate_hz * exposure_s)
        gone = atoms[lost]
        present.flat[gone] = -np.log1p(-u[lost]) / (rate_hz * exposure_s)
        self._static.flat[gone] = False
        self.counters.lost_imaging += int(gone.size)
        return present


_NO_TRACKS = np.zeros((0, 4), dtype=np.float32)


# --- kernels ---------------------------------------------------------------------------------------------
# Each one replays its ``World._*_reference`` method step for step: the same conditions evaluated on the same
# state (all of a stage's reads before its writes, as the vectorised code does), and the same uniforms read
# from ``u`` in the same order (the order of ``np.flatnonzero`` over the same masks).


@njit(cache=True, nogil=True)
def _vacuum(
    static: np.ndarray, held: np.ndarray, next_hit_s: np.ndarray, t_s: float, u: np.ndarray, pos: int, lifetime_s: float
) -> tuple[int, int, bool]:
    """Background-gas hits up to ``t_s``, earliest first; each hit empties its site and draws the site's next
    hit (an exponential wait from ``u``). Returns ``(pos, lost, done)``; ``done`` is False when ``u`` ran out."""
    n = static.size
    hits = next_hit_s.reshape(2 * n)
    static_flat = static.reshape(n)
    held_flat = held.reshape(n)
    lost = 0
    while pos < u.size:
        k = np.argmin(hits)
        if hits[k] > t_s:
            return pos, lost, True
        grid = static_flat if k < n else held_flat
        site = k % n
        if grid[site]:
            grid[site] = False
            lost += 1
        hits[k] -= lifetime_s * np.log1p(-u[pos])
        pos += 1
    return pos, lost, False


_kernels_warm = False  # set once _warm_up has run in this process


def _warm_up() -> None:
    """Compile (or load from the cache) every kernel now, not during the first shot; no state is touched."""
    global _kernels_warm
    if _kernels_warm:
        return
    grid = np.zeros((1, 1), dtype=bool)
    u = np.zeros(4)
    one = np.array([[0, 0, 1, 1]], dtype=np.float32)
    _vacuum(grid, grid.copy(), np.full((2, 1, 1), np.inf), 0.0, u, 0, 1.0)
    st = MoveState(1, 1)
    ev = mm.new_events()
    mm.tweezer_slot(
        one, one, 0.5, 1, st.static, st.held, st.held_mark, st.ids, st.atom_stats, False, st.arrivals, st.tweezers,
        u, 0, False, 1.0, False, 1.0, ev,
    )  # fmt: skip
    mm.chain_slot(one, 0.5, st.static[0], st.ids[0, 0], st.atom_stats, False, st.chain_scratch, u, 0, False, 1.0, ev)
    _kernels_warm = True
