"""The simulated lab's ground truth: which traps hold atoms, and what the AOD tones do to them.

Two kinds of trap, following ``array.trap_source``:

- ``slm``: static traps on an ``ny x nx`` grid (from an SLM) plus mobile tweezers at the product set of the
  y tracks x the x tracks of a slot. Tweezer depth is ``amp_x * amp_y``. A tweezer whose depth rises from off
  to on over a static atom extracts it (one transfer); a loaded tweezer carries its atom (one step per slot
  in which it moves); a loaded tweezer whose depth falls to off implants the atom into the trap below (one
  transfer; if that trap is occupied both atoms are lost: a light-assisted collision). A loaded tweezer that
  is simply gone at the start of a slot drops its atom.
- ``aod``: a 1D chain whose traps are the x tones themselves. An atom follows its tone's track (a step when it
  moves); a tone that fades out while holding an atom loses it, and an atom where no tone starts is lost.

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
world's own arrays (``_tweezer_slot``, ``_chain_slot``, ``_vacuum``) instead of a dozen small numpy ops. The
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
from engine.config import SystemConfig
from engine.devices import Clock

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
        self.nx = self.ny = 0
        self.vacuum_lifetime_s = 0.0
        self.lossless = True
        self._t_s = clock.now_s() if clock is not None else 0.0
        self._first_hit_s = np.inf  # no hit process yet: ``reconfigure`` starts one
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
        lossless = sim.lossless if lossless is None else lossless
        vacuum_changed = (sim.vacuum_lifetime_s, lossless) != (self.vacuum_lifetime_s, self.lossless)
        self.vacuum_lifetime_s = sim.vacuum_lifetime_s
        self.lossless = lossless
        self._configure_imaging(config)
        if (arr.ny, arr.nx) != (self.ny, self.nx):
            self.nx, self.ny = arr.nx, arr.ny
            self._static = np.zeros((self.ny, self.nx), dtype=bool)
            self._held = np.zeros((self.ny, self.nx), dtype=bool)  # atoms in tweezers, at the tweezer's site
            self._covered = np.zeros((self.ny, self.nx), dtype=bool)  # kernel scratch
            self._flags = np.zeros((0, 6), dtype=np.bool_)  # kernel scratch, one row per tweezer
            self._chain_scratch = np.zeros((2, self.nx), dtype=np.int64)
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

    def _draw_first_hits(self) -> None:
        """Start every site's background-gas process afresh at the world's time (memoryless, so no bias).

        ``_next_hit_s[0]`` are the static traps, ``[1]`` the tweezer sites; infinite when lossless.
        """
        self._next_hit_s = np.full((2, self.ny, self.nx), np.inf)
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
                self._static, self._held, self._next_hit_s, t_s, u.buf, u.pos, self.vacuum_lifetime_s
            )
            self.counters.lost_vacuum += lost
        self._first_hit_s = float(self._next_hit_s.min())

    def _vacuum_reference(self, t_s: float) -> None:
        hits = self._next_hit_s.reshape(2, -1)
        grids = (self._static.reshape(-1), self._held.reshape(-1))
        while True:
            kind, site = np.unravel_index(np.argmin(hits), hits.shape)
            if hits[kind, site] > t_s:
                break
            if grids[kind][site]:
                grids[kind][site] = False
                self.counters.lost_vacuum += 1
            hits[kind, site] -= self.vacuum_lifetime_s * np.log1p(-self._vacuum_draws.take(1)[0])
        self._first_hit_s = float(hits.min())

    def _survive(self, n: int, p: float) -> np.ndarray:
        if self.lossless or p >= 1.0:
            return np.ones(n, dtype=bool)
        return self._move_draws.take(n) < p

    # --- slots -----------------------------------------------------------------------------------------

    def apply_slot(self, x_tracks: np.ndarray, y_tracks: np.ndarray | None) -> None:
        """Apply one decoded slot: ``*_tracks`` are ``[m, 4]`` rows ``(site0, site1, amp0, amp1)``."""
        self.counters.slots += 1
        if self.trap_source == "aod":
            if self.reference:
                self._apply_chain_reference(x_tracks)
            else:
                self._apply_chain(x_tracks)
        else:
            yt = y_tracks if y_tracks is not None else _NO_TRACKS
            if self.reference:
                self._apply_tweezers_reference(x_tracks, yt)
            else:
                self._apply_tweezers(x_tracks, yt)

    def _apply_chain(self, tracks: np.ndarray) -> None:
        """The chain conveyor as one kernel call (``_chain_slot``; reference: ``_apply_chain_reference``)."""
        atoms = self._static[0]
        if not atoms.any():
            return
        tracks = np.ascontiguousarray(tracks, dtype=np.float32)
        draw = not self.lossless and self.survival_step < 1.0
        u = self._move_draws
        if draw and u.buf.size - u.pos < self.nx:
            u.ensure(self.nx)
        pos, steps, lost_step, lost_collision, lost_dropped, lost_released = _chain_slot(
            tracks, atoms, self._chain_scratch, u.buf, u.pos, draw, self.survival_step
        )
        u.pos = pos
        c = self.counters
        c.steps += steps
        c.lost_step += lost_step
        c.lost_collision += lost_collision
        c.lost_dropped += lost_dropped
        c.lost_released += lost_released

    def _apply_chain_reference(self, tracks: np.ndarray) -> None:
        atoms = self._static[0]
        if not atoms.any():
            return
        c = self.counters
        s0 = tracks[:, 0].astype(np.int64)
        s1 = tracks[:, 1].astype(np.int64)
        on0 = tracks[:, 2] >= FULL_FRACTION
        on1 = tracks[:, 3] >= FULL_FRACTION
        trap_of = np.full(self.nx, -1, dtype=np.int64)  # track holding site k at the start
        live = np.flatnonzero(on0)
        trap_of[s0[live]] = live
        src = np.flatnonzero(atoms)
        t = trap_of[src]
        c.lost_dropped += int(np.count_nonzero(t < 0))
        src, t = src[t >= 0], t[t >= 0]
        released = ~on1[t]
        c.lost_released += int(np.count_nonzero(released))
        src, t = src[~released], t[~released]
        dst = s1[t]
        moved = dst != src
        c.steps += int(moved.sum())
        keep = np.ones(src.size, dtype=bool)
        keep[moved] = self._survive(int(moved.sum()), self.survival_step)
        c.lost_step += int(np.count_nonzero(~keep))
        dst = dst[keep]
        new = np.zeros(self.nx, dtype=np.int64)
        np.add.at(new, dst, 1)
        c.lost_collision += int(new[new > 1].sum())
        atoms[:] = new == 1

    def _apply_tweezers(self, xt: np.ndarray, yt: np.ndarray) -> None:
        """The product-set tweezers as one kernel call (``_tweezer_slot``; reference: ``_apply_tweezers_reference``)."""
        xt = np.ascontiguousarray(xt, dtype=np.float32)
        yt = np.ascontiguousarray(yt, dtype=np.float32)
        n_tweezers = xt.shape[0] * yt.shape[0]
        if self._flags.shape[0] < n_tweezers:
            self._flags = np.zeros((max(n_tweezers, 4 * self.nx * self.ny), 6), dtype=np.bool_)
        draw_transfer = not self.lossless and self.survival_transfer < 1.0
        draw_step = not self.lossless and self.survival_step < 1.0
        u = self._move_draws
        need = 3 * n_tweezers  # at most one extraction, one step and one implant per tweezer
        if (draw_transfer or draw_step) and u.buf.size - u.pos < need:
            u.ensure(need)
        pos, transfers, steps, lost_transfer, lost_step, lost_collision, lost_dropped = _tweezer_slot(
            xt, yt, self._static, self._held, self._covered, self._flags, u.buf, u.pos,
            draw_transfer, self.survival_transfer, draw_step, self.survival_step,
        )  # fmt: skip
        u.pos = pos
        c = self.counters
        c.transfers += transfers
        c.steps += steps
        c.lost_transfer += lost_transfer
        c.lost_step += lost_step
        c.lost_collision += lost_collision
        c.lost_dropped += lost_dropped

    def _apply_tweezers_reference(self, xt: np.ndarray, yt: np.ndarray) -> None:
        c = self.counters
        if xt.shape[0] == 0 or yt.shape[0] == 0:
            lost = int(self._held.sum())
            c.lost_dropped += lost
            self._held[:] = False
            return
        # the product set: tweezer (i, j) = y track i x x track j
        r0 = yt[:, 0].astype(np.int64)[:, None]
        r1 = yt[:, 1].astype(np.int64)[:, None]
        c0 = xt[:, 0].astype(np.int64)[None, :]
        c1 = xt[:, 1].astype(np.int64)[None, :]
        shape = (yt.shape[0], xt.shape[0])
        r0, r1, c0, c1 = (np.broadcast_to(v, shape).ravel() for v in (r0, r1, c0, c1))
        on0 = (np.multiply.outer(yt[:, 2], xt[:, 2]) >= FULL_FRACTION).ravel()
        on1 = (np.multiply.outer(yt[:, 3], xt[:, 3]) >= FULL_FRACTION).ravel()

        held = self._held
        covered = np.zeros_like(held)
        covered[r0[on0], c0[on0]] = True
        dropped = held & ~covered
        c.lost_dropped += int(dropped.sum())
        loaded = on0 & held[r0, c0]
        held[:] = False

        # extraction: depth rises over a static atom (taken from the start site)
        ext = ~on0 & on1 & self._static[r0, c0]
        n_ext = int(ext.sum())
        if n_ext:
            c.transfers += n_ext
            self._static[r0[ext], c0[ext]] = False
            ok = self._survive(n_ext, self.survival_transfer)
            c.lost_transfer += int(np.count_nonzero(~ok))
            idx = np.flatnonzero(ext)[ok]
            loaded[idx] = True

        # transport: one step per loaded tweezer that moves
        moving = loaded & ((r0 != r1) | (c0 != c1))
        n_mov = int(moving.sum())
        if n_mov:
            c.steps += n_mov
            ok = self._survive(n_mov, self.survival_step)
            c.lost_step += int(np.count_nonzero(~ok))
            loaded[np.flatnonzero(moving)[~ok]] = False

        # still loaded at the end: stays held, or is implanted where the depth falls
        stay = loaded & on1
        held[r1[stay], c1[stay]] = True
        imp = np.flatnonzero(loaded & ~on1)
        if imp.size:
            c.transfers += int(imp.size)
            ok = self._survive(int(imp.size), self.survival_transfer)
            c.lost_transfer += int(np.count_nonzero(~ok))
            imp = imp[ok]
            rr, cc = r1[imp], c1[imp]
            clash = self._static[rr, cc]
            c.lost_collision += 2 * int(clash.sum())
            self._static[rr[clash], cc[clash]] = False
            self._static[rr[~clash], cc[~clash]] = True

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


@njit(cache=True, nogil=True)
def _tweezer_slot(
    xt: np.ndarray,
    yt: np.ndarray,
    static: np.ndarray,
    held: np.ndarray,
    covered: np.ndarray,
    flags: np.ndarray,
    u: np.ndarray,
    pos: int,
    draw_transfer: bool,
    p_transfer: float,
    draw_step: bool,
    p_step: float,
) -> tuple[int, int, int, int, int, int, int]:
    """One slm slot (tweezer t = y track i x x track j, t = i * mx + j, as ``ravel`` orders the product set).

    Returns ``(pos, transfers, steps, lost_transfer, lost_step, lost_collision, lost_dropped)``.
    ``flags[t]`` columns: on at start, on at end, loaded, extracted, implant clashes, implanted.
    """
    transfers = steps = lost_transfer = lost_step = lost_collision = lost_dropped = 0
    my = yt.shape[0]
    mx = xt.shape[0]
    if my == 0 or mx == 0:
        for r in range(held.shape[0]):
            for c in range(held.shape[1]):
                if held[r, c]:
                    lost_dropped += 1
                    held[r, c] = False
        return pos, transfers, steps, lost_transfer, lost_step, lost_collision, lost_dropped
    n = my * mx
    full = np.float32(0.5)
    covered[:, :] = False
    for i in range(my):
        r0 = int(yt[i, 0])
        for j in range(mx):
            c0 = int(xt[j, 0])
            t = i * mx + j
            # depth = amp_y * amp_x in float32, as np.multiply.outer of the float32 tracks computes it
            on0 = np.float32(yt[i, 2] * xt[j, 2]) >= full
            flags[t, 0] = on0
            flags[t, 1] = np.float32(yt[i, 3] * xt[j, 3]) >= full
            if on0:
                covered[r0, c0] = True
    for r in range(held.shape[0]):
        for c in range(held.shape[1]):
            if held[r, c] and not covered[r, c]:
                lost_dropped += 1
    # loaded (held before) and extraction candidates read the state before anything is written
    n_ext = 0
    for i in range(my):
        r0 = int(yt[i, 0])
        for j in range(mx):
            c0 = int(xt[j, 0])
            t = i * mx + j
            flags[t, 2] = flags[t, 0] and held[r0, c0]
            ext = (not flags[t, 0]) and flags[t, 1] and static[r0, c0]
            flags[t, 3] = ext
            if ext:
                n_ext += 1
    held[:, :] = False

    # extraction: depth rises over a static atom (taken from the start site)
    if n_ext:
        transfers += n_ext
        for t in range(n):
            if flags[t, 3]:
                static[int(yt[t // mx, 0]), int(xt[t % mx, 0])] = False
        for t in range(n):
            if flags[t, 3]:
                ok = True
                if draw_transfer:
                    ok = u[pos] < p_transfer
                    pos += 1
                if ok:
                    flags[t, 2] = True
                else:
                    lost_transfer += 1

    # transport: one step per loaded tweezer that moves
    for t in range(n):
        i = t // mx
        j = t % mx
        moving = flags[t, 2] and (int(yt[i, 0]) != int(yt[i, 1]) or int(xt[j, 0]) != int(xt[j, 1]))
        if moving:
            steps += 1
            ok = True
            if draw_step:
                ok = u[pos] < p_step
                pos += 1
            if not ok:
                lost_step += 1
                flags[t, 2] = False

    # still loaded at the end: stays held, or is implanted where the depth falls
    n_imp = 0
    for t in range(n):
        flags[t, 5] = False
        if flags[t, 2]:
            r1 = int(yt[t // mx, 1])
            c1 = int(xt[t % mx, 1])
            if flags[t, 1]:
                held[r1, c1] = True
            else:
                transfers += 1
                ok = True
                if draw_transfer:
                    ok = u[pos] < p_transfer
                    pos += 1
                if ok:
                    flags[t, 5] = True
                    n_imp += 1
                else:
                    lost_transfer += 1
    if n_imp:
        # every implant sees the static traps as they were before any implant of this slot
        for t in range(n):
            flags[t, 4] = flags[t, 5] and static[int(yt[t // mx, 1]), int(xt[t % mx, 1])]
        for t in range(n):
            if flags[t, 4]:
                lost_collision += 2
                static[int(yt[t // mx, 1]), int(xt[t % mx, 1])] = False
        for t in range(n):
            if flags[t, 5] and not flags[t, 4]:
                static[int(yt[t // mx, 1]), int(xt[t % mx, 1])] = True
    return pos, transfers, steps, lost_transfer, lost_step, lost_collision, lost_dropped


@njit(cache=True, nogil=True)
def _chain_slot(
    tracks: np.ndarray, atoms: np.ndarray, scratch: np.ndarray, u: np.ndarray, pos: int, draw: bool, p_step: float
) -> tuple[int, int, int, int, int, int]:
    """One aod-chain slot. Returns ``(pos, steps, lost_step, lost_collision, lost_dropped, lost_released)``."""
    nx = atoms.size
    trap_of = scratch[0]  # track holding site k at the start (the last such track, as a fancy assignment)
    new = scratch[1]  # atoms arriving at each site
    trap_of[:] = -1
    new[:] = 0
    full = np.float32(0.5)
    for t in range(tracks.shape[0]):
        if tracks[t, 2] >= full:
            trap_of[int(tracks[t, 0])] = t
    steps = lost_step = lost_collision = lost_dropped = lost_released = 0
    for k in range(nx):
        if not atoms[k]:
            continue
        t = trap_of[k]
        if t < 0:
            lost_dropped += 1
            continue
        if not tracks[t, 3] >= full:
            lost_released += 1
            continue
        dst = int(tracks[t, 1])
        if dst != k:
            steps += 1
            if draw:
                ok = u[pos] < p_step
                pos += 1
                if not ok:
                    lost_step += 1
                    continue
        new[dst] += 1
    for k in range(nx):
        if new[k] > 1:
            lost_collision += new[k]
        atoms[k] = new[k] == 1
    return pos, steps, lost_step, lost_collision, lost_dropped, lost_released


def _warm_up() -> None:
    """Compile (or load from the cache) every kernel now, not during the first shot; no state is touched."""
    if _warm_up.done:  # type: ignore[attr-defined]
        return
    grid = np.zeros((1, 1), dtype=bool)
    u = np.zeros(4)
    one = np.array([[0, 0, 1, 1]], dtype=np.float32)
    _vacuum(grid, grid.copy(), np.full((2, 1, 1), np.inf), 0.0, u, 0, 1.0)
    _tweezer_slot(one, one, grid, grid.copy(), grid.copy(), np.zeros((1, 6), np.bool_), u, 0, False, 1.0, False, 1.0)
    _chain_slot(one, np.zeros(1, dtype=bool), np.zeros((2, 1), np.int64), u, 0, False, 1.0)
    _warm_up.done = True  # type: ignore[attr-defined]


_warm_up.done = False  # type: ignore[attr-defined]
