"""The sample decoder: hand-synthesized slots of every kind decode into the right tone tracks."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.sim.decode import DecodeConfigError, SampleDecoder
from drivers.sim.world import World
from sim_signals import (
    chain_config,
    chain_moves,
    chain_shift,
    grid_config,
    move,
    ramp_down,
    ramp_up,
    static,
    synth_slots,
    tanh_shape,
)


def moves_of(t: np.ndarray) -> list[tuple[int, int]]:
    return sorted((int(r[0]), int(r[1])) for r in t if r[0] != r[1])


def kinds_of(t: np.ndarray) -> dict[int, str]:
    """Non-moving tracks by site: 'static', 'up' (0 -> full), 'down' (full -> 0)."""
    out = {}
    for r in t:
        if r[0] == r[1]:
            on0, on1 = r[2] >= 0.5, r[3] >= 0.5
            out[int(r[0])] = {(True, True): "static", (False, True): "up", (True, False): "down"}.get((on0, on1), "off")
    return out


CHAIN_CONFIGS = {
    "624MS-1MHz": chain_config(64),
    # 133 MHz is near this card's Nyquist: the DAC-compensated comb needs a lower amplitude to fit full scale
    "313.6MS-1MHz": chain_config(64, waveforms={"sample_rate_hz": 313.6e6}, array={"x_tones": {"amplitude": 0.012}}),
    "624MS-0.5MHz": chain_config(64, array={"x_tones": {"spacing_hz": 0.5e6}}),
    "tanh6-1MHz": chain_config(64, waveforms={"shape": "tanh", "shape_sharpness": 6.0}),
}


@pytest.mark.parametrize("name", CHAIN_CONFIGS)
def test_chain_block_shifts_with_fades(name: str) -> None:
    cfg = CHAIN_CONFIGS[name]
    shape = tanh_shape(6.0) if cfg.waveforms.shape == "tanh" else None
    dec = SampleDecoder(cfg)
    cases = [
        ([10, 11, 12, 13, 14], +1),
        ([10, 11, 12, 13, 14], -1),
        ([0, 1, 2], +1),  # block at the left edge
        ([62, 63], -1),  # block at the right edge
        ([30], +1),
        ([], 0),  # idle: every trap static
    ]
    slots = [(chain_shift(64, m, d), None) for m, d in cases]
    kw = {"shape": shape} if shape else {}
    d = dec.decode(synth_slots(cfg, slots, **kw))
    assert d.n_slots == len(cases)
    for i, (movers, delta) in enumerate(cases):
        xt, yt = d.slot(i)
        assert yt is None
        assert moves_of(xt) == [(k, k + delta) for k in movers], d.describe(i)
        kinds = kinds_of(xt)
        for k in range(64):
            if k in movers:
                continue
            if movers and k == (max(movers) + 1 if delta > 0 else min(movers) - 1):
                assert kinds.get(k) in ("down", "off", None), (k, d.describe(i))  # entered: fades out
            elif movers and k == (min(movers) if delta > 0 else max(movers)):
                assert kinds.get(k) in ("up", "off", None), (k, d.describe(i))  # vacated: fades in
            else:
                assert kinds.get(k) == "static", (k, d.describe(i))
    assert not d.stationary


def test_chain_two_blocks_opposite_directions() -> None:
    cfg = CHAIN_CONFIGS["624MS-1MHz"]
    tones = chain_moves(64, {3: -1, 4: -1, 20: +1, 21: +1, 22: +1})
    d = SampleDecoder(cfg).decode(synth_slots(cfg, [(tones, None)]))
    assert moves_of(d.slot(0)[0]) == [(3, 2), (4, 3), (20, 21), (21, 22), (22, 23)]


GRID = grid_config(8, 6)


def test_grid_extract_shift_implant_tracks() -> None:
    slots = [
        ([ramp_up(1), ramp_up(2), ramp_up(6)], [ramp_up(0), ramp_up(3)]),  # extract product set
        ([move(1, -1), move(2, +1), static(6)], [move(0, +1), static(3)]),  # shift: mixed deltas
        ([ramp_down(0), ramp_down(3), ramp_down(6)], [ramp_down(1), ramp_down(3)]),  # implant
        ([], []),  # silence (slm idle)
    ]
    d = SampleDecoder(GRID).decode(synth_slots(GRID, slots))
    x0, y0 = d.slot(0)
    assert kinds_of(x0) == {1: "up", 2: "up", 6: "up"} and kinds_of(y0) == {0: "up", 3: "up"}
    x1, y1 = d.slot(1)
    assert moves_of(x1) == [(1, 0), (2, 3)] and kinds_of(x1) == {6: "static"}
    assert moves_of(y1) == [(0, 1)] and kinds_of(y1) == {3: "static"}
    x2, y2 = d.slot(2)
    assert kinds_of(x2) == {0: "down", 3: "down", 6: "down"} and kinds_of(y2) == {1: "down", 3: "down"}
    x3, y3 = d.slot(3)
    assert x3.shape[0] == 0 and y3.shape[0] == 0
    for t in (x1, y1):
        assert np.all(np.abs(t[:, 2:] - 1) < 0.2)  # amplitudes normalised to the static amplitude


def test_stationary_segments() -> None:
    hold = synth_slots(GRID, [([static(1), static(4)], [static(2)])] * 2)
    assert SampleDecoder(GRID).decode(hold).stationary
    silence = np.zeros((3 * GRID.waveforms.slot_samples, 2), np.int16)
    assert SampleDecoder(GRID).decode(silence).stationary


def test_decoded_grid_moves_atoms_and_collides() -> None:
    world = World(GRID, lossless=True)
    occ = np.zeros((6, 8), bool)
    occ[0, [1, 2]] = True
    occ[3, 6] = True
    occ[1, 3] = True  # the atom from (0, 2) will be implanted onto (1, 3): collision
    world.set_occupancy(occ)
    slots = [
        ([ramp_up(1), ramp_up(2)], [ramp_up(0)]),
        ([move(1, -1), move(2, +1)], [move(0, +1)]),
        ([ramp_down(0), ramp_down(3)], [ramp_down(1)]),
    ]
    world.apply_segment(SampleDecoder(GRID).decode(synth_slots(GRID, slots)))
    want = np.zeros((6, 8), bool)
    want[1, 0] = True
    want[3, 6] = True
    assert np.array_equal(world.occupancy(), want)
    assert world.counters.lost_collision == 2 and world.counters.steps == 2


def test_decoded_chain_moves_atoms() -> None:
    cfg = chain_config(16)
    world = World(cfg, lossless=True)
    world.set_occupancy(np.array([[0, 1, 1, 0, 1] + [0] * 11], bool))
    slots = [(chain_shift(16, [1, 2], +1), None), (chain_shift(16, [4], -1), None)]
    world.apply_segment(SampleDecoder(cfg).decode(synth_slots(cfg, slots)))
    # slot 0: atoms 1,2 -> 2,3; slot 1: site 3 fades out under its atom (released) while atom 4 moves onto 3
    assert np.flatnonzero(world.occupancy()[0]).tolist() == [2, 3]
    assert world.counters.lost_released == 1 and world.counters.steps == 3


def test_resolution_condition_is_enforced() -> None:
    with pytest.raises(DecodeConfigError, match="slot_duration_s \\* spacing_hz"):
        SampleDecoder(chain_config(16, array={"x_tones": {"spacing_hz": 0.3e6}}))
    with pytest.raises(DecodeConfigError, match="shape_sharpness"):
        SampleDecoder(chain_config(16, waveforms={"shape": "tanh", "shape_sharpness": 20.0}))
    with pytest.raises(DecodeConfigError, match="2 AWG channel"):
        SampleDecoder(GRID, n_channels=1)


def test_decoding_a_200_slot_two_channel_plan_is_fast() -> None:
    # y reaches 143 MHz, near this card's Nyquist: the DAC-compensated comb needs a lower amplitude to fit
    cfg = grid_config(32, 64, waveforms={"sample_rate_hz": 313.6e6}, array={"y_tones": {"amplitude": 0.012}})
    base = synth_slots(
        cfg,
        [
            ([ramp_up(k) for k in range(0, 32, 2)], [ramp_up(k) for k in range(0, 64, 3)]),
            ([move(k, 1) for k in range(0, 32, 2)], [move(k, 1) for k in range(0, 64, 3)]),
            ([ramp_down(k) for k in range(1, 32, 2)], [ramp_down(k) for k in range(1, 64, 3)]),
            ([], []),
        ],
    )
    plan = np.tile(base, (50, 1))
    dec = SampleDecoder(cfg)
    dec.decode(base)  # compile
    t0 = time.perf_counter()
    d = dec.decode(plan)
    dt = time.perf_counter() - t0
    assert d.n_slots == 200
    assert moves_of(d.slot(1)[0]) == [(k, k + 1) for k in range(0, 32, 2)]
    assert dt < 0.5, f"decoding took {dt:.3f} s"
