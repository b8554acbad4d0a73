"""The numba kernels of the bank (package-internal): one tone into a row, slot lookup (slots -> table keys,
with run keys for prefix rows), the exact int32 row sum and the int16 conversion.

Every kernel is ``njit(cache=True, nogil=True)`` over buffers the bank allocates once; the plain-numpy
specification they implement is ``engine.waveforms.shapes`` (tested against ``tests/waveform_reference.py``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from engine.operations import EXTRACT, IDLE, IMPLANT, SHIFT
from engine.waveforms.shapes import (
    _CUM,
    _ENV_IN,
    _ENV_OUT,
    _G,
    _S,
    FADE_IN,
    FADE_OUT,
    HEAD_DOWN,
    HEAD_UP,
    INNER_UP,
    ISO_DOWN,
    ISO_UP,
    MOVE_DOWN,
    MOVE_UP,
    N_KINDS,
    RAMP_DOWN,
    RAMP_UP,
    STATIC,
    TAIL_DOWN,
    TAIL_UP,
)

# run keys (prefix rows): _RUN0 + (row of P[b] << _RUN_SHIFT) + row of P[a]; below _RUN0 are single rows
_RUN_SHIFT = 20
_RUN_MASK = (1 << _RUN_SHIFT) - 1
_RUN0 = 1 << 44

# lookup error codes (returned as code + 16 * slot); the last two are about the call, not a slot
_E_CHAIN_KIND, _E_SITE, _E_ORDER, _E_DELTA, _E_EDGE, _E_CROSS, _E_KIND, _E_ARRAY, _E_KEYS = range(1, 10)
_ERRORS = {
    _E_CHAIN_KIND: "a chain (trap_source 'aod') slot must be SHIFT or IDLE",
    _E_SITE: "a tone site is outside the axis",
    _E_ORDER: "tone sites must be listed in strictly ascending order",
    _E_DELTA: "a delta must be -1, 0 or +1",
    _E_EDGE: "a tone would move off the end of the axis",
    _E_CROSS: "tones would cross or merge (their end sites are not strictly ascending)",
    _E_KIND: "unknown operation kind",
}



@njit(cache=True, nogil=True)
def _tone(kind, k, n_sites, cyc, amp, phi, shp, scale, inv_q, out):
    """One tone of ``kind`` at site ``k`` into ``out[N]``: table units ``rint(value * inv_q)`` when
    ``inv_q > 0`` (int16 table rows and direct synthesis alike, so both paths give identical rows), else the
    exact value in counts (float64 ``out``, for tests)."""
    n_samp = out.shape[0]
    quantize = inv_q > 0.0
    w = 2.0 * np.pi / n_samp
    m0 = cyc[k] % n_samp
    p0 = phi[k]
    a0 = amp[k] * scale
    if kind == MOVE_UP or kind == MOVE_DOWN or kind >= INNER_UP:
        up = kind == MOVE_UP or kind == INNER_UP or kind == HEAD_UP or kind == TAIL_UP or kind == ISO_UP
        d = 1 if up else -1
        k2 = k + d
        if k2 < 0 or k2 >= n_sites:
            out[:] = 0
            return
        chain = kind >= INNER_UP
        head = kind == HEAD_UP or kind == HEAD_DOWN or kind == ISO_UP or kind == ISO_DOWN
        tail = kind == TAIL_UP or kind == TAIL_DOWN or kind == ISO_UP or kind == ISO_DOWN
        m2 = cyc[k2] % n_samp
        p2 = phi[k2]
        dm = float(cyc[k2] - cyc[k])
        a1 = amp[k2] * scale
        raw_end = p0 + w * dm * shp[_CUM, n_samp]
        x = p2 - raw_end
        c = np.pi - ((np.pi - x) % (2.0 * np.pi))  # wrap into (-pi, pi]
        for n in range(n_samp):
            st = w * ((m0 * n) % n_samp)
            th = p0 + st + w * dm * shp[_CUM, n] + c * shp[_G, n]
            v = (a0 + (a1 - a0) * shp[_S, n]) * math.sin(th)
            if chain:
                # minus the static tone of the source, plus its fade-in if vacated
                e = shp[_ENV_IN, n] - 1.0 if tail else -1.0
                v += a0 * e * math.sin(p0 + st)
                if head:  # the entered site's static tone fades out
                    v += a1 * (shp[_ENV_OUT, n] - 1.0) * math.sin(p2 + w * ((m2 * n) % n_samp))
            if quantize:
                out[n] = np.rint(v * inv_q)
            else:
                out[n] = v
        return
    # stationary tones: static phase times an envelope e0 + e1 * env[n]
    e0 = 1.0
    e1 = 0.0
    env = _S
    if kind == RAMP_UP:
        e0, e1, env = 0.0, 1.0, _S
    elif kind == RAMP_DOWN:
        e0, e1, env = 1.0, -1.0, _S
    elif kind == FADE_OUT:
        e0, e1, env = 0.0, 1.0, _ENV_OUT
    elif kind == FADE_IN:
        e0, e1, env = 0.0, 1.0, _ENV_IN
    for n in range(n_samp):
        v = a0 * (e0 + e1 * shp[env, n]) * math.sin(p0 + w * ((m0 * n) % n_samp))
        if quantize:
            out[n] = np.rint(v * inv_q)
        else:
            out[n] = v


@njit(cache=True, nogil=True)
def _lookup_chain(kind, x_site, x_delta, first, count, keys, key_of):
    """Chain (``trap_source = "aod"``) slots ``first..first+count-1`` to keys (``_lookup_slots``); a chain has
    one axis, as wide as ``key_of``, and no prefix rows: the slm arguments it passes are never read."""
    return _lookup_slots(
        kind, x_site, x_delta, x_site, x_delta, first, count, keys, key_of, key_of[0], key_of.shape[1], 0, True
    )


@njit(cache=True, nogil=True)
def _lookup_slm(kind, x_site, x_delta, y_site, y_delta, first, count, keys, key_of, prow_of, nx, ny):
    """slm slots ``first..first+count-1`` to keys (``_lookup_slots``)."""
    return _lookup_slots(kind, x_site, x_delta, y_site, y_delta, first, count, keys, key_of, prow_of, nx, ny, False)


@njit(cache=True, nogil=True, inline="always")
def _lookup_slots(kind, x_site, x_delta, y_site, y_delta, first, count, keys, key_of, prow_of, nx, ny, chain):
    """Slots ``first..first+count-1`` to keys; returns 0, or ``code + 16 * slot`` on an invalid slot or
    ``_E_ARRAY`` / ``_E_KEYS`` when the plan's array or ``keys`` does not fit the bank.

    Slot j's keys start at ``j * (2 + nx + ny)``: two counts, then the keys. One slot loop for a chain and
    for slm, so that the slot layout, idle slots and the error codes have one home; each kernel above inlines
    it with ``chain`` a constant, so the branch it does not take is compiled away (one kernel with all the
    arguments cost a chain plan's lookup ~0.3 us more, in the argument dispatch alone).

    A chain slot (``ny = 0``) is ``[n_movers, 0, one key per mover...]``. A mover's kind (inner, head, tail,
    isolated; up or down) depends on the tones before and after it in the slot's list, which the loop carries
    along (each tone is read once) and combines with arithmetic and selects rather than branches: which
    variant a mover is follows the atoms, not a pattern the branch predictor could learn.

    An slm slot is ``[n_ch0, n_ch1, ch0 keys..., ch1 keys...]``. A key in ``[0, _RUN0)`` is a table row; a
    negative key ``-(code + 1)`` is synthesized directly, ``code = (axis * N_KINDS + kind) * n_max + site``
    (``key_of`` holds both, by ``[axis * N_KINDS + kind, site]``; a chain's movers are keyed the same way); a
    key ``>= _RUN0`` is a run of consecutive sites ``[a, b)`` of one (axis, kind) with a prefix block:
    ``_RUN0 + (p_b << _RUN_SHIFT) + p_a``, with ``p_a``, ``p_b`` rows of the prefix table. A run replaces two
    or more single keys, so a slot never has more keys than tones and the stride stays a bound.
    """
    stride = 2 + nx + ny
    if x_site.shape[1] != nx or (not chain and y_site.shape[1] != ny):
        return _E_ARRAY
    if keys.shape[0] < count * stride:
        return _E_KEYS
    for j in range(count):
        i = first + j
        kb = j * stride
        kd = kind[i]
        keys[kb] = 0
        keys[kb + 1] = 0
        if kd == IDLE:
            continue
        if chain:
            if kd != SHIFT:
                return _E_CHAIN_KIND + 16 * i
            m = 0
            kp, dp = -2, 0  # the tone before (none yet: a site no tone can start from or reach)
            k, d = x_site[i, 0], x_delta[i, 0]
            for t in range(nx):
                if k < 0:
                    break
                kn, dn = (x_site[i, t + 1], x_delta[i, t + 1]) if t + 1 < nx else (-1, 0)  # the tone after
                if k >= nx:
                    return _E_SITE + 16 * i
                if d < -1 or d > 1:
                    return _E_DELTA + 16 * i
                if k + d < 0 or k + d >= nx:
                    return _E_EDGE + 16 * i
                if k <= kp:
                    return _E_ORDER + 16 * i
                if k + d <= kp + dp:
                    return _E_CROSS + 16 * i
                if d != 0:
                    up = d > 0
                    # head: the site ahead is not a source, so it is entered and fades out
                    head = (kn if up else kp) != k + d
                    # tail: no tone behind moves in the same way, so the vacated site fades in
                    tail = ((kp if up else kn) != k - d) | ((dp if up else dn) != d)
                    # INNER_UP, INNER_DOWN, HEAD_UP, ..., ISO_DOWN in that order: + 2 head + 4 tail + 1 down
                    keys[kb + 2 + m] = key_of[INNER_UP + 2 * head + 4 * tail + (1 - up), k]
                    m += 1
                kp, dp = k, d
                k, d = kn, dn
            keys[kb] = m
        else:
            m = 0
            if kd != EXTRACT and kd != SHIFT and kd != IMPLANT:
                return _E_KIND + 16 * i
            for axis in range(2):
                sites = x_site if axis == 0 else y_site
                deltas = x_delta if axis == 0 else y_delta
                n_ax = nx if axis == 0 else ny
                m_axis = m
                run_m = 0  # key position, first site, length and kind of the run being built
                run_a = 0
                run_len = 0
                run_kind = -1
                for t in range(n_ax):
                    k = sites[i, t]
                    if k < 0:
                        break
                    if k >= n_ax:
                        return _E_SITE + 16 * i
                    if t > 0 and k <= sites[i, t - 1]:
                        return _E_ORDER + 16 * i
                    if kd == EXTRACT:
                        tk = RAMP_UP
                    elif kd == IMPLANT:
                        tk = RAMP_DOWN
                    else:
                        d = deltas[i, t]
                        if d < -1 or d > 1:
                            return _E_DELTA + 16 * i
                        if k + d < 0 or k + d >= n_ax:
                            return _E_EDGE + 16 * i
                        if t > 0 and k + d <= sites[i, t - 1] + deltas[i, t - 1]:
                            return _E_CROSS + 16 * i
                        tk = STATIC if d == 0 else (MOVE_UP if d > 0 else MOVE_DOWN)
                    p0 = prow_of[axis * N_KINDS + tk]
                    if p0 >= 0 and run_len > 0 and tk == run_kind and k == run_a + run_len:
                        run_len += 1
                        keys[kb + 2 + run_m] = _RUN0 + ((p0 + run_a + run_len) << _RUN_SHIFT) + (p0 + run_a)
                        m = run_m + 1
                    else:
                        run_m = m
                        run_a = k
                        run_len = 1
                        run_kind = tk
                        keys[kb + 2 + m] = key_of[axis * N_KINDS + tk, k]
                        m += 1
                keys[kb + axis] = m - m_axis
    return 0


@njit(cache=True, nogil=True)
def _failsafe_keys(kind, x_site, x_delta, y_site, y_delta, i, keys, key_of, prow_of, nx, ny):
    """Keys (one slot, as ``_lookup_slots``) of steady full tones where slm slot ``i`` leaves them."""
    keys[0] = 0
    keys[1] = 0
    kd = kind[i]
    if kd != EXTRACT and kd != SHIFT:
        return
    m = 0
    for axis in range(2):
        sites = x_site if axis == 0 else y_site
        deltas = x_delta if axis == 0 else y_delta
        n_ax = nx if axis == 0 else ny
        m_axis = m
        p0 = prow_of[axis * N_KINDS + STATIC]
        run_m = 0
        run_a = 0
        run_len = 0
        for t in range(n_ax):
            k = sites[i, t]
            if k < 0:
                break
            end = k + deltas[i, t] if kd == SHIFT else k
            if end < 0 or end >= n_ax:
                continue
            if p0 >= 0 and run_len > 0 and end == run_a + run_len:
                run_len += 1
                keys[2 + run_m] = _RUN0 + ((p0 + run_a + run_len) << _RUN_SHIFT) + (p0 + run_a)
                m = run_m + 1
            else:
                run_m = m
                run_a = end
                run_len = 1
                keys[2 + m] = key_of[axis * N_KINDS + STATIC, end]
                m += 1
        keys[axis] = m - m_axis


@njit(cache=True, nogil=True)
def _row(key, table, scratch, n_sites, cyc, amp, phi, shp, n_max, scale, inv_q):
    """int16 row of ``key``: the table row, or ``scratch`` filled by direct synthesis."""
    if key >= 0:
        return table[key]
    code = -key - 1
    site = code % n_max
    ak = code // n_max
    ax = ak // N_KINDS
    _tone(ak % N_KINDS, site, n_sites[ax], cyc[ax], amp[ax], phi[ax], shp, scale, inv_q[ax], scratch)
    return scratch


@njit(cache=True, nogil=True)
def _add_rows(acc, first, r0, r1, r2, r3, g):
    """``acc (=|+=) r0 + ... + r_{g-1}`` in int32 (exact; the order does not matter)."""
    n_samp = acc.shape[0]
    if g == 4:
        if first:
            for n in range(n_samp):
                acc[n] = (np.int32(r0[n]) + np.int32(r1[n])) + (np.int32(r2[n]) + np.int32(r3[n]))
        else:
            for n in range(n_samp):
                acc[n] += (np.int32(r0[n]) + np.int32(r1[n])) + (np.int32(r2[n]) + np.int32(r3[n]))
    elif g == 3:
        if first:
            for n in range(n_samp):
                acc[n] = (np.int32(r0[n]) + np.int32(r1[n])) + np.int32(r2[n])
        else:
            for n in range(n_samp):
                acc[n] += (np.int32(r0[n]) + np.int32(r1[n])) + np.int32(r2[n])
    elif g == 2:
        if first:
            for n in range(n_samp):
                acc[n] = np.int32(r0[n]) + np.int32(r1[n])
        else:
            for n in range(n_samp):
                acc[n] += np.int32(r0[n]) + np.int32(r1[n])
    else:
        if first:
            for n in range(n_samp):
                acc[n] = np.int32(r0[n])
        else:
            for n in range(n_samp):
                acc[n] += np.int32(r0[n])


@njit(cache=True, nogil=True)
def _add_run(acc, first, pb, pa):
    """``acc (=|+=) pb - pa``: a run's rows from two int32 prefix rows (exact)."""
    n_samp = acc.shape[0]
    if first:
        for n in range(n_samp):
            acc[n] = pb[n] - pa[n]
    else:
        for n in range(n_samp):
            acc[n] += pb[n] - pa[n]


@njit(cache=True, nogil=True)
def _render(keys, count, stride, n_ch, base, q, table, prefix, n_sites, cyc, amp, phi, shp, n_max, scale, inv_q,
            acc, scratch, out):
    """Write ``count`` slots to ``out`` (int16[>= count*N, n_ch], C-contiguous): per channel,
    ``rint(base[ch] + q[ch] * sum of the slot's int16 rows)``, clipped to +-32767. A run key adds
    ``P[b] - P[a]`` (two int32 prefix rows), the same int32 sum as its rows one by one."""
    n_samp = acc.shape[1]
    flat = out.reshape(-1)
    for j in range(count):
        kb = j * stride
        off = kb + 2
        for ch in range(n_ch):
            nk = keys[kb + ch]
            a = acc[ch]
            if nk == 0:
                a[:] = 0
            t = 0
            while t < nk:
                key = keys[off + t]
                if key >= _RUN0:
                    v = key - _RUN0
                    _add_run(a, t == 0, prefix[v >> _RUN_SHIFT], prefix[v & _RUN_MASK])
                    t += 1
                    continue
                g = 1  # up to four single rows, up to the next run
                while g < 4 and t + g < nk and keys[off + t + g] < _RUN0:
                    g += 1
                r0 = _row(keys[off + t], table, scratch[0], n_sites, cyc, amp, phi, shp, n_max, scale, inv_q)
                r1 = r0
                r2 = r0
                r3 = r0
                if g >= 2:
                    r1 = _row(keys[off + t + 1], table, scratch[1], n_sites, cyc, amp, phi, shp, n_max, scale, inv_q)
                if g >= 3:
                    r2 = _row(keys[off + t + 2], table, scratch[2], n_sites, cyc, amp, phi, shp, n_max, scale, inv_q)
                if g >= 4:
                    r3 = _row(keys[off + t + 3], table, scratch[3], n_sites, cyc, amp, phi, shp, n_max, scale, inv_q)
                _add_rows(a, t == 0, r0, r1, r2, r3, g)
                t += g
            off += nk
        o = j * n_samp * n_ch
        if n_ch == 1:
            _convert1(flat[o : o + n_samp], base[0], acc[0], q[0])
        else:
            _convert2(flat[o : o + 2 * n_samp], base[0], acc[0], q[0], base[1], acc[1], q[1])


@njit(cache=True, nogil=True)
def _convert1(out, b0, a0, q0):
    """``out[n] = rint(b0[n] + q0 * a0[n])``, clipped to +-32767."""
    lo = np.float32(-32767.0)
    hi = np.float32(32767.0)
    for n in range(a0.shape[0]):
        v = b0[n] + q0 * np.float32(a0[n])
        out[n] = np.int16(np.rint(min(max(v, lo), hi)))


@njit(cache=True, nogil=True)
def _convert2(out, b0, a0, q0, b1, a1, q1):
    """Two channels, interleaved: ``out[2n + ch]``."""
    lo = np.float32(-32767.0)
    hi = np.float32(32767.0)
    for n in range(a0.shape[0]):
        v0 = b0[n] + q0 * np.float32(a0[n])
        v1 = b1[n] + q1 * np.float32(a1[n])
        out[2 * n] = np.int16(np.rint(min(max(v0, lo), hi)))
        out[2 * n + 1] = np.int16(np.rint(min(max(v1, lo), hi)))

