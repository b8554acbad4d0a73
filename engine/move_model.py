"""The move model: what AOD tones do to atoms in one waveform slot, written once for the validator and the world.

The plan validator (``engine/solvers/validate.py``, losses off) and the simulated lab
(``drivers/sim/world.py``, tracks decoded from the AWG's samples, losses drawn from its random numbers)
both call these kernels, so a plan the validator accepts is exactly a plan the simulated lab carries out.

A slot is described per axis by **tone tracks** ``[m, 4]`` rows ``(start site, end site, start amplitude
fraction, end amplitude fraction)`` (float32, the format ``drivers/sim/decode.py`` reports).

``slm`` trap source (static traps on an ``ny x nx`` grid, crossed AODs): the tweezers are the product set
y track i x x track j, at every intersection, loaded or not; a tweezer is at full depth where
``amp_y * amp_x >= full_fraction``. Per slot:

1. the first full-depth tweezer over a held atom at the start holds it on; a held atom that no full-depth
   tweezer covers is **dropped** (lost);
2. a loaded tweezer that moves carries its atom one **step** (may lose it);
3. at the end of the slot, per tweezer:
   - loaded, at a site with another atom (in a static trap or another tweezer): **collision**
     (light-assisted; every atom there is lost);
   - loaded, ramping down: **implant** into the trap below (a transfer, may lose it);
   - loaded, still on: keeps holding the atom;
   - empty, at full depth over an occupied static trap: takes the atom (a transfer, may lose it). If the
     tweezer ramped up there this is a **pick-up** (an extract); if it was already at full depth and arrived
     (or sat) there it is a **capture**: the atom now moves with the tweezer (a **drag**) until it ramps down.

**Interstitial routing** (``engine/routing.py``): the grids are of positions, ``half`` per site, and only
positions even on both axes (``r % half == c % half == 0``) are traps. Elsewhere a tweezer is in a channel:
no static atom is ever there, so it captures and collides with nothing in the traps, and a loaded tweezer that
ramps down there **releases** its atom into no trap (lost). With ``half = 1`` every position is a trap.

``aod`` trap source (a 1D chain whose traps are the x tones): an atom follows the track that starts on its
site at full depth (a step when it moves); a track that fades out holding an atom **releases** it (lost); an
atom no track starts on is **dropped**; two atoms arriving at one site **collide**.

Events are summed into an ``int64[N_EVENTS]`` array (indices ``EV_*``); the ``EV_FIRST_*`` entries hold the
flat index of the first site where a fault happened (-1 if none), for the validator's messages. Random
numbers are read from a pre-drawn buffer ``u`` from position ``pos`` (the world's ``_Uniforms``): step draws
in tweezer order first, then transfer draws in tweezer order, one per draw that the loss model asks for.

With ``track_ids`` the kernels also carry atom identities (``ids``: -1 where empty) and
count per atom (``atom_stats[a]``: steps, pick-ups + captures, captures) for the validator's accounting.
The plain-numpy twins (``*_reference``) are the readable statement of the same rules, kept to test the
kernels against.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from engine.operations import EXTRACT, IDLE, IMPLANT, SHIFT

__all__ = [
    "EV_CAPTURED", "EV_DRAGGED", "EV_FIRST_CAPTURE", "EV_FIRST_COLLISION", "EV_FIRST_DROP", "EV_IMPLANTED",
    "EV_LOST_COLLISION", "EV_LOST_DROPPED", "EV_LOST_RELEASED", "EV_LOST_STEP", "EV_LOST_TRANSFER",
    "EV_PICKED", "EV_STEPS", "N_EVENTS", "STAT_CAPTURES", "STAT_PICKUPS", "STAT_STEPS", "MoveState",
    "chain_slot", "chain_slot_reference", "new_events", "operation_tracks", "replay_operations",
    "tweezer_slot", "tweezer_slot_reference",
]  # fmt: skip

EV_PICKED = 0  # atoms taken by a tweezer ramping up over them (extract)
EV_CAPTURED = 1  # atoms taken by a full-depth tweezer arriving (or sitting) over them
EV_IMPLANTED = 2  # atoms left in a static trap by a tweezer ramping down
EV_STEPS = 3  # one-site moves of held atoms
EV_DRAGGED = 4  # captured atoms that then moved at least one site
EV_LOST_TRANSFER = 5
EV_LOST_STEP = 6
EV_LOST_COLLISION = 7
EV_LOST_DROPPED = 8  # held atoms no tweezer holds any more (slm), atoms no tone starts on (aod)
EV_LOST_RELEASED = 9  # aod chain: a tone fading out while it holds an atom; slm: a tweezer ramping down in a channel
EV_FIRST_COLLISION = 10
EV_FIRST_CAPTURE = 11
EV_FIRST_DROP = 12  # first dropped or released atom
N_EVENTS = 13

STAT_STEPS = 0
STAT_PICKUPS = 1  # pick-ups and captures: every time the atom was taken into a tweezer
STAT_CAPTURES = 2

#: held_mark values: how a held atom got into its tweezer
_MARK_PICKED = 0
_MARK_CAPTURED = 1
_MARK_DRAGGED = 2


def new_events() -> np.ndarray:
    """A zeroed event record (the ``EV_FIRST_*`` sites at -1: none yet)."""
    ev = np.zeros(N_EVENTS, dtype=np.int64)
    ev[EV_FIRST_COLLISION:] = -1
    return ev


class MoveState:
    """Atoms in static traps and tweezers plus the kernels' scratch, allocated once per array size.

    ``static``/``held``: ``bool[ny, nx]`` (held atoms sit at their tweezer's site); ``held_mark``: how each
    held atom was taken (for the drag count); ``ids`` (static, held) and ``atom_stats``: identities and
    per-atom counts, used only when a kernel runs with ``track_ids``. (The simulated world keeps its own
    ``static``/``held`` grids and uses the rest.)
    """

    def __init__(self, ny: int, nx: int) -> None:
        self.static = np.zeros((ny, nx), dtype=np.bool_)
        self.held = np.zeros((ny, nx), dtype=np.bool_)
        self.held_mark = np.zeros((ny, nx), dtype=np.int8)
        self.ids = np.full((2, ny, nx), -1, dtype=np.int64)  # atom ids in static traps, in tweezers
        self.atom_stats = np.zeros((0, 3), dtype=np.int64)
        self.arrivals = np.zeros((ny, nx), dtype=np.int64)
        self.tweezers = np.zeros((ny * nx, 8), dtype=np.int64)  # per tweezer scratch of tweezer_slot
        self.chain_scratch = np.zeros((3, nx), dtype=np.int64)
        self.y_tracks = np.zeros((ny, 4), dtype=np.float32)
        self.x_tracks = np.zeros((2 * nx, 4), dtype=np.float32)  # a chain slot: a track per site + fade-ins

    def load(self, occupancy: np.ndarray) -> None:
        """Atoms at ``occupancy``, numbered in row-major order; nothing held; per-atom counts zeroed."""
        occ = np.asarray(occupancy, dtype=bool)
        self.static[:] = occ
        self.held[:] = False
        self.held_mark[:] = 0
        self.ids[:] = -1
        n = int(occ.sum())
        self.ids[0][occ] = np.arange(n)
        self.atom_stats = np.zeros((n, 3), dtype=np.int64)


# --- crossed AODs over static traps ----------------------------------------------------------------------


@njit(cache=True, nogil=True)
def _transfer_kept(u: np.ndarray, pos: int, p_transfer: float, draw_transfer: bool) -> tuple[bool, int]:
    """Whether a transfer (pick-up or implant) keeps its atom, drawing the uniform ``u[pos]`` against
    ``p_transfer`` when ``draw_transfer``, and the index of the next draw."""
    if not draw_transfer:
        return True, pos
    return u[pos] < p_transfer, pos + 1


@njit(cache=True, nogil=True)
def tweezer_slot(
    yt: np.ndarray, xt: np.ndarray, full_fraction: float, half: int,
    static: np.ndarray, held: np.ndarray, held_mark: np.ndarray, ids: np.ndarray, atom_stats: np.ndarray,
    track_ids: bool, arrivals: np.ndarray, tw: np.ndarray, u: np.ndarray, pos: int,
    draw_transfer: bool, p_transfer: float, draw_step: bool, p_step: float,
    events: np.ndarray,
) -> int:  # fmt: skip
    """One slot of product-set tweezers (tweezer t = y track i x x track j, t = i * mx + j). Returns ``pos``.

    Scratch: ``arrivals`` (per site) and ``tw`` (at least ``my * mx`` rows; columns: full depth at start, at end,
    loaded, moved, atom id, how it was taken, end row, end column). ``ids[0]``/``ids[1]``: identities of the atoms
    in static traps / tweezers (read and written only with ``track_ids``). Tracks from a real slot never share a
    site; when they do, the first tweezer (in ``t`` order) over a site takes what is there, and every atom that ends
    a slot at a site together with another is lost in the collision.
    """
    ny, nx = static.shape
    my = yt.shape[0]
    mx = xt.shape[0]
    full = np.float32(full_fraction)
    n = my * mx
    arrivals[:, :] = 0
    for i in range(my):
        for j in range(mx):
            t = i * mx + j
            tw[t, 0] = np.float32(yt[i, 2] * xt[j, 2]) >= full
            tw[t, 1] = np.float32(yt[i, 3] * xt[j, 3]) >= full
            tw[t, 6] = int(yt[i, 1])  # the site the tweezer ends the slot over
            tw[t, 7] = int(xt[j, 1])
            tw[t, 3] = int(yt[i, 0]) != tw[t, 6] or int(xt[j, 0]) != tw[t, 7]
            tw[t, 2] = False
            if tw[t, 0]:
                r0 = int(yt[i, 0])
                c0 = int(xt[j, 0])
                # 1. the first full-depth tweezer over a held atom holds it from now on
                if held[r0, c0]:
                    held[r0, c0] = False
                    tw[t, 2] = True
                    tw[t, 5] = held_mark[r0, c0]
                    if track_ids:
                        tw[t, 4] = ids[1, r0, c0]
    # held atoms that no full-depth tweezer covers at the start fall out
    for r in range(ny):
        for c in range(nx):
            if held[r, c]:
                events[EV_LOST_DROPPED] += 1
                if events[EV_FIRST_DROP] < 0:
                    events[EV_FIRST_DROP] = r * nx + c
                held[r, c] = False
    # 2. transport: one step per loaded tweezer that moves
    for t in range(n):
        if tw[t, 2] and tw[t, 3]:
            events[EV_STEPS] += 1
            if tw[t, 5] == _MARK_CAPTURED:
                events[EV_DRAGGED] += 1
                tw[t, 5] = _MARK_DRAGGED
            if track_ids:
                atom_stats[tw[t, 4], STAT_STEPS] += 1
            if draw_step:
                ok = u[pos] < p_step
                pos += 1
                if not ok:
                    events[EV_LOST_STEP] += 1
                    tw[t, 2] = False
    # 3a. collisions: a site where a loaded tweezer ends with another atom (static or loaded) loses them all
    for t in range(n):
        if tw[t, 2]:
            arrivals[tw[t, 6], tw[t, 7]] += 1
    for t in range(n):
        r1 = tw[t, 6]
        c1 = tw[t, 7]
        if tw[t, 2] and arrivals[r1, c1] + static[r1, c1] >= 2:
            events[EV_LOST_COLLISION] += 1
            if events[EV_FIRST_COLLISION] < 0:
                events[EV_FIRST_COLLISION] = r1 * nx + c1
            tw[t, 2] = False
            if static[r1, c1]:
                events[EV_LOST_COLLISION] += 1
                static[r1, c1] = False
    # 3b. per tweezer: implant, keep holding, or take the atom below
    for t in range(n):
        r1 = tw[t, 6]
        c1 = tw[t, 7]
        on1 = tw[t, 1]
        if tw[t, 2]:
            if not on1 and (r1 % half != 0 or c1 % half != 0):  # ramped down in a channel: no trap below
                events[EV_LOST_RELEASED] += 1
                if events[EV_FIRST_DROP] < 0:
                    events[EV_FIRST_DROP] = r1 * nx + c1
            elif not on1:
                events[EV_IMPLANTED] += 1
                ok, pos = _transfer_kept(u, pos, p_transfer, draw_transfer)
                if ok:
                    static[r1, c1] = True
                    if track_ids:
                        ids[0, r1, c1] = tw[t, 4]
                else:
                    events[EV_LOST_TRANSFER] += 1
            else:
                held[r1, c1] = True
                held_mark[r1, c1] = tw[t, 5]
                if track_ids:
                    ids[1, r1, c1] = tw[t, 4]
        elif on1 and static[r1, c1] and arrivals[r1, c1] == 0:
            captured = tw[t, 0]
            if captured:
                events[EV_CAPTURED] += 1
                if events[EV_FIRST_CAPTURE] < 0:
                    events[EV_FIRST_CAPTURE] = r1 * nx + c1
            else:
                events[EV_PICKED] += 1
            static[r1, c1] = False
            a = -1
            if track_ids:
                a = ids[0, r1, c1]
                ids[0, r1, c1] = -1
                atom_stats[a, STAT_PICKUPS] += 1
                if captured:
                    atom_stats[a, STAT_CAPTURES] += 1
            ok, pos = _transfer_kept(u, pos, p_transfer, draw_transfer)
            if ok:
                held[r1, c1] = True
                held_mark[r1, c1] = _MARK_CAPTURED if captured else _MARK_PICKED
                if track_ids:
                    ids[1, r1, c1] = a
            else:
                events[EV_LOST_TRANSFER] += 1
    return pos


def _first_per_site(candidates: np.ndarray, sites: np.ndarray) -> np.ndarray:
    """Of tweezer indices ``candidates`` (ascending), the first one at each distinct site, ascending."""
    _, first = np.unique(sites[candidates], return_index=True)
    return np.sort(candidates[first])


def tweezer_slot_reference(
    yt: np.ndarray, xt: np.ndarray, full_fraction: float, half: int, static: np.ndarray, held: np.ndarray,
    mark: np.ndarray, u: np.ndarray, pos: int, p_transfer: float | None, p_step: float | None, events: np.ndarray,
) -> int:
    """``tweezer_slot`` in plain numpy (atom bookkeeping without identities); ``p_* = None``: no draws."""
    nx = static.shape[1]
    full = np.float32(full_fraction)
    my, mx = yt.shape[0], xt.shape[0]
    r0 = np.repeat(yt[:, 0].astype(np.int64), mx)
    r1 = np.repeat(yt[:, 1].astype(np.int64), mx)
    c0 = np.tile(xt[:, 0].astype(np.int64), my)
    c1 = np.tile(xt[:, 1].astype(np.int64), my)
    start, end = r0 * nx + c0, r1 * nx + c1
    on0 = (np.multiply.outer(yt[:, 2], xt[:, 2]).astype(np.float32) >= full).ravel()
    on1 = (np.multiply.outer(yt[:, 3], xt[:, 3]).astype(np.float32) >= full).ravel()
    moved = (r0 != r1) | (c0 != c1)
    static_flat, held_flat, mark_flat = static.reshape(-1), held.reshape(-1), mark.reshape(-1)

    # 1. the first full-depth tweezer over each held atom takes it over; the rest of the held atoms fall out
    loaded = np.zeros(start.size, dtype=bool)
    holders = _first_per_site(np.flatnonzero(on0), start)
    holders = holders[held_flat[start[holders]]]
    loaded[holders] = True
    tw_mark = np.zeros(start.size, dtype=np.int8)
    tw_mark[holders] = mark_flat[start[holders]]
    held_flat[start[holders]] = False
    dropped = np.flatnonzero(held_flat)
    events[EV_LOST_DROPPED] += dropped.size
    if dropped.size and events[EV_FIRST_DROP] < 0:
        events[EV_FIRST_DROP] = dropped[0]
    held[:] = False

    # 2. transport
    stepping = np.flatnonzero(loaded & moved)
    events[EV_STEPS] += stepping.size
    first_drag = stepping[tw_mark[stepping] == _MARK_CAPTURED]
    events[EV_DRAGGED] += first_drag.size
    tw_mark[first_drag] = _MARK_DRAGGED
    if p_step is not None and stepping.size:
        lost = stepping[u[pos : pos + stepping.size] >= p_step]
        pos += stepping.size
        events[EV_LOST_STEP] += lost.size
        loaded[lost] = False

    # 3a. collisions: every atom at a site where a loaded tweezer ends together with another atom
    arrivals = np.bincount(end[loaded], minlength=static_flat.size)
    crowded = arrivals + static_flat >= 2
    collide = loaded & crowded[end]
    hit = np.flatnonzero(collide)
    events[EV_LOST_COLLISION] += hit.size + int(np.count_nonzero(static_flat & crowded))
    if hit.size and events[EV_FIRST_COLLISION] < 0:
        events[EV_FIRST_COLLISION] = end[hit[0]]
    static_flat[crowded] = False
    loaded &= ~collide

    # 3b. implant (a release in a channel: lost), keep holding, or take the atom below (the first full-depth
    # tweezer over it)
    released = loaded & ~on1 & ((r1 % half != 0) | (c1 % half != 0))
    events[EV_LOST_RELEASED] += int(np.count_nonzero(released))
    if released.any() and events[EV_FIRST_DROP] < 0:
        events[EV_FIRST_DROP] = end[np.flatnonzero(released)[0]]
    loaded &= ~released
    implant = loaded & ~on1
    keep = loaded & on1
    take = np.zeros(start.size, dtype=bool)
    take[_first_per_site(np.flatnonzero(~loaded & on1 & static_flat[end] & (arrivals[end] == 0)), end)] = True
    captured = take & on0
    events[EV_PICKED] += int(np.count_nonzero(take & ~on0))
    events[EV_CAPTURED] += int(np.count_nonzero(captured))
    first_capture = np.flatnonzero(captured)
    if first_capture.size and events[EV_FIRST_CAPTURE] < 0:
        events[EV_FIRST_CAPTURE] = end[first_capture[0]]
    events[EV_IMPLANTED] += int(np.count_nonzero(implant))
    drawn = np.flatnonzero(implant | take)  # transfer draws in tweezer order
    ok = np.ones(start.size, dtype=bool)
    if p_transfer is not None and drawn.size:
        ok[drawn] = u[pos : pos + drawn.size] < p_transfer
        pos += drawn.size
    events[EV_LOST_TRANSFER] += int(np.count_nonzero(~ok[drawn]))
    static_flat[end[take]] = False
    static_flat[end[implant & ok]] = True
    got = take & ok
    held_flat[end[keep | got]] = True
    mark_flat[end[keep]] = tw_mark[keep]
    mark_flat[end[got]] = np.where(on0[got], _MARK_CAPTURED, _MARK_PICKED)
    return pos


# --- a 1D AOD chain ----------------------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def chain_slot(
    tracks: np.ndarray, full_fraction: float, atoms: np.ndarray, row_id: np.ndarray, atom_stats: np.ndarray,
    track_ids: bool, scratch: np.ndarray, u: np.ndarray, pos: int, draw: bool, p_step: float, events: np.ndarray,
) -> int:
    """One slot of the chain (``atoms``: ``bool[nx]``, the chain's sites; ``row_id``: their identities).
    Returns ``pos``."""
    nx = atoms.size
    trap_of = scratch[0]  # track holding site k at the start (the last such track)
    new = scratch[1]  # atoms arriving at each site
    new_id = scratch[2]
    trap_of[:] = -1
    new[:] = 0
    new_id[:] = -1
    full = np.float32(full_fraction)
    for t in range(tracks.shape[0]):
        if tracks[t, 2] >= full:
            trap_of[int(tracks[t, 0])] = t
    for k in range(nx):
        if not atoms[k]:
            continue
        t = trap_of[k]
        if t < 0 or not tracks[t, 3] >= full:
            events[EV_LOST_DROPPED if t < 0 else EV_LOST_RELEASED] += 1
            if events[EV_FIRST_DROP] < 0:
                events[EV_FIRST_DROP] = k
            continue
        dst = int(tracks[t, 1])
        if dst != k:
            events[EV_STEPS] += 1
            if track_ids:
                atom_stats[row_id[k], STAT_STEPS] += 1
            if draw:
                ok = u[pos] < p_step
                pos += 1
                if not ok:
                    events[EV_LOST_STEP] += 1
                    continue
        new[dst] += 1
        if track_ids:
            new_id[dst] = row_id[k]
    for k in range(nx):
        if new[k] > 1:
            events[EV_LOST_COLLISION] += new[k]
            if events[EV_FIRST_COLLISION] < 0:
                events[EV_FIRST_COLLISION] = k
        atoms[k] = new[k] == 1
        if track_ids:
            row_id[k] = new_id[k] if new[k] == 1 else -1
    return pos


def chain_slot_reference(
    tracks: np.ndarray, full_fraction: float, atoms: np.ndarray, u: np.ndarray, pos: int, p_step: float | None,
    events: np.ndarray,
) -> int:
    """``chain_slot`` in plain numpy (no identities); ``p_step = None``: no draws."""
    full = np.float32(full_fraction)
    s0 = tracks[:, 0].astype(np.int64)
    s1 = tracks[:, 1].astype(np.int64)
    on0 = tracks[:, 2] >= full
    on1 = tracks[:, 3] >= full
    trap_of = np.full(atoms.size, -1, dtype=np.int64)
    live = np.flatnonzero(on0)
    trap_of[s0[live]] = live
    src = np.flatnonzero(atoms)
    t = trap_of[src]
    lost = np.sort(np.concatenate([src[t < 0], src[t >= 0][~on1[t[t >= 0]]]]))
    if lost.size and events[EV_FIRST_DROP] < 0:
        events[EV_FIRST_DROP] = lost[0]
    events[EV_LOST_DROPPED] += int(np.count_nonzero(t < 0))
    src, t = src[t >= 0], t[t >= 0]
    released = ~on1[t]
    events[EV_LOST_RELEASED] += int(np.count_nonzero(released))
    src, t = src[~released], t[~released]
    dst = s1[t]
    moved = dst != src
    events[EV_STEPS] += int(moved.sum())
    keep = np.ones(src.size, dtype=bool)
    if p_step is not None and moved.any():
        keep[moved] = u[pos : pos + int(moved.sum())] < p_step
        pos += int(moved.sum())
    events[EV_LOST_STEP] += int(np.count_nonzero(~keep))
    new = np.bincount(dst[keep], minlength=atoms.size)
    crowded = np.flatnonzero(new > 1)
    events[EV_LOST_COLLISION] += int(new[crowded].sum())
    if crowded.size and events[EV_FIRST_COLLISION] < 0:
        events[EV_FIRST_COLLISION] = crowded[0]
    atoms[:] = new == 1
    return pos


# --- planned operations as tracks --------------------------------------------------------------------------


@njit(cache=True, nogil=True)
def operation_tracks(
    kind: int, sites: np.ndarray, deltas: np.ndarray, n_sites: int, chain: bool, out: np.ndarray
) -> int:
    """The tone tracks one axis of a planned slot plays (what the waveform stage renders, as the simulated
    AWG's decoder would report it); returns the number of rows written to ``out``.

    Crossed AODs: ``EXTRACT`` ramps the listed tones up in place, ``SHIFT`` moves them at full amplitude,
    ``IMPLANT`` ramps them down, ``IDLE`` plays nothing. Chain (``chain``): every site has a tone; the listed
    ones move by their delta, a site a mover enters fades out and a site one leaves (and none enters) fades in.
    """
    m = 0
    if not chain:
        if kind == IDLE:
            return 0
        a0 = np.float32(0.0) if kind == EXTRACT else np.float32(1.0)
        a1 = np.float32(0.0) if kind == IMPLANT else np.float32(1.0)
        for k in range(sites.size):
            s = sites[k]
            if s < 0:
                break
            out[m, 0] = s
            out[m, 1] = s + (deltas[k] if kind == SHIFT else 0)
            out[m, 2] = a0
            out[m, 3] = a1
            m += 1
        return m
    if kind == IDLE:  # the hold waveform: every trap's tone, steady
        for k in range(n_sites):
            out[k, 0] = k
            out[k, 1] = k
            out[k, 2] = 1.0
            out[k, 3] = 1.0
        return n_sites
    # per site: is it a listed tone (and where does it go), is it entered by a moving tone
    listed = np.zeros(n_sites, dtype=np.bool_)
    entered = np.zeros(n_sites, dtype=np.bool_)
    dest = np.arange(n_sites)
    for k in range(sites.size):
        s = sites[k]
        if s < 0:
            break
        listed[s] = True
        dest[s] = s + deltas[k]
        if deltas[k] != 0 and 0 <= dest[s] < n_sites:
            entered[dest[s]] = True
    for s in range(n_sites):
        out[m, 0] = s
        out[m, 1] = dest[s]
        out[m, 2] = 1.0
        out[m, 3] = 0.0 if entered[s] and not listed[s] else 1.0
        m += 1
        if listed[s] and dest[s] != s and not entered[s]:
            # the site the tone leaves fades in a tone of its own (off at the start, so it holds nothing yet)
            out[m, 0] = s
            out[m, 1] = s
            out[m, 2] = 0.0
            out[m, 3] = 1.0
            m += 1
    return m


@njit(cache=True, nogil=True)
def replay_operations(
    kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray,
    first: int, stop: int, chain: bool, half: int,
    static: np.ndarray, held: np.ndarray, held_mark: np.ndarray, ids: np.ndarray, atom_stats: np.ndarray,
    track_ids: bool, arrivals: np.ndarray, tw: np.ndarray, chain_scratch: np.ndarray, yt: np.ndarray,
    xt: np.ndarray, events: np.ndarray,
    stop_on_fault: bool, stop_on_capture: bool,
) -> int:  # fmt: skip
    """Play planned slots ``first..stop-1`` through the move model, losses off.

    Returns the index of the slot after which the first fault (collision, dropped or released atom) showed
    when ``stop_on_fault`` (or the first capture, ``stop_on_capture``), else ``stop``. Captures are not
    faults of the model: whether a plan accounts for them is the validator's question.
    """
    ny, nx = static.shape
    u = np.zeros(1)
    row_static = static[0]
    row_id = ids[0, 0]
    for i in range(first, stop):
        k = int(kind[i])
        if chain:
            m = operation_tracks(k, x_site[i], x_delta[i], nx, True, xt)
            chain_slot(xt[:m], 1.0, row_static, row_id, atom_stats, track_ids, chain_scratch, u, 0, False, 1.0, events)
        else:
            my = operation_tracks(k, y_site[i], y_delta[i], ny, False, yt)
            mx = operation_tracks(k, x_site[i], x_delta[i], nx, False, xt)
            tweezer_slot(yt[:my], xt[:mx], 0.5, half, static, held, held_mark, ids, atom_stats, track_ids, arrivals, tw,
                         u, 0, False, 1.0, False, 1.0, events)  # fmt: skip
        if stop_on_fault and (
            events[EV_LOST_COLLISION] > 0 or events[EV_LOST_DROPPED] > 0 or events[EV_LOST_RELEASED] > 0
        ):
            return i
        if stop_on_capture and events[EV_CAPTURED] > 0:
            return i
    return stop
