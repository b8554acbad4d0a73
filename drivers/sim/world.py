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

Loss: ``survival_transfer`` per extract/implant, ``survival_step`` per one-site move, and vacuum lifetime
``exp(-dt / tau)`` per atom over clock time (``elapse_to``). ``lossless`` turns all of it off (collisions
and dropped atoms still lose atoms: they are mistakes, not noise). Counters record every cause.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from drivers.sim.decode import FULL_FRACTION, DecodedSegment
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


class World:
    """Atoms in static traps and in mobile tweezers; seeded, so a shot replays exactly."""

    def __init__(
        self,
        config: SystemConfig,
        *,
        clock: Clock | None = None,
        rng: np.random.Generator | None = None,
        lossless: bool | None = None,
    ) -> None:
        self.clock = clock
        self.rng = rng if rng is not None else np.random.default_rng(config.sim.seed)
        self.counters = WorldCounters()
        self.nx = self.ny = 0
        self.reconfigure(config, lossless=lossless)
        self._t_s = clock.now_s() if clock is not None else 0.0

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

    # --- state -----------------------------------------------------------------------------------------

    def load(self) -> np.ndarray:
        """Empty every trap and tweezer, then fill each trap with probability ``loading_probability``."""
        self._static[:] = self.rng.random((self.ny, self.nx)) < self.loading_probability
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
        for grid in (self._static, self._held):
            idx = np.flatnonzero(grid)
            if idx.size:
                gone = idx[self.rng.random(idx.size) >= p_keep]
                grid.flat[gone] = False
                self.counters.lost_vacuum += int(gone.size)

    def _survive(self, n: int, p: float) -> np.ndarray:
        if self.lossless or p >= 1.0:
            return np.ones(n, dtype=bool)
        return self.rng.random(n) < p

    # --- slots -----------------------------------------------------------------------------------------

    def apply_slot(self, x_tracks: np.ndarray, y_tracks: np.ndarray | None) -> None:
        """Apply one decoded slot: ``*_tracks`` are ``[m, 4]`` rows ``(site0, site1, amp0, amp1)``."""
        self.counters.slots += 1
        if self.trap_source == "aod":
            self._apply_chain(x_tracks)
        else:
            self._apply_tweezers(x_tracks, y_tracks if y_tracks is not None else np.zeros((0, 4), np.float32))

    def _apply_chain(self, tracks: np.ndarray) -> None:
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
