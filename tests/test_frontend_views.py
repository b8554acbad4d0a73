"""The dashboard's state transforms, without viser: atom map, timing table, history, camera picture, presets."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from engine.config import SystemConfig, load_config
from engine.psf import trap_positions_px
from engine.timing import PAPER_TABLE1_MS, STAGES
from frontend import views
from frontend.dashboard import target_presets

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def chain_positions(n: int = 8) -> np.ndarray:
    return np.stack([8.0 + 16.0 * np.arange(n), np.full(n, 8.0)], axis=1)


def states(svg: str) -> list[str]:
    return re.findall(r'data-state="(\w+)"', svg)


def test_atom_map_marks_every_trap_by_what_it_needs() -> None:
    svg = views.atom_map_svg(["11001010"], ["00111100"], chain_positions())
    assert states(svg) == ["spare", "spare", "missing", "missing", "in_place", "missing", "spare", "empty"]
    assert svg.startswith("<svg") and svg.endswith("</svg>")
    assert svg.count(f'fill="{views.COLOURS["target_bg"]}"') == 4  # the target region is shaded


def test_atom_map_rejects_mismatched_sizes() -> None:
    with pytest.raises(ValueError, match="8 traps"):
        views.atom_map_svg(["1100"], ["0011"], chain_positions())


def test_trap_layout_follows_the_camera_orientation() -> None:
    """grid-16x32 images its 32 rows along the camera's x axis: the picture is 32 wide and 16 tall."""
    cfg = load_config(EXAMPLES / "grid-16x32.yaml")
    cells, across, down = views.trap_layout(trap_positions_px(cfg))
    assert (across, down) == (32, 16)
    assert tuple(cells[1]) == (0, 1) and tuple(cells[cfg.array.nx]) == (1, 0)  # next column down, next row right
    _, across, down = views.trap_layout(chain_positions(64))
    assert (across, down) == (64, 1)


def _shot(outcome: str = "success") -> dict:
    return {
        "shot_id": 7,
        "outcome": outcome,
        "fault": None,
        "target": ["00111100"],
        "truth": {"target_filled": outcome == "success"},
        "cycles": [
            {"occupancy": ["11011010"], "atoms": 5, "defects": 1, "n_slots": 3,
             "stage_us": {"I.acquire": 25_000.0, "III.solve": 5.0}},
            {"occupancy": ["00111100"], "atoms": 4, "defects": 0, "n_slots": 0, "stage_us": {"I.acquire": 25_500.0}},
        ],
    }


def test_shot_html_shows_each_cycle_and_the_outcome() -> None:
    html = views.shot_html(_shot(), chain_positions())
    assert 'id="atom-map" data-shot-id="7" data-outcome="success" data-cycles="2"' in html
    assert html.count('class="atom-map"') == 2
    assert "loaded (before rearranging): 5 atoms" in html and "1 missing" in html
    assert "final image (after 1 rearrangement): 4 atoms" in html and "all 4 in place" in html
    assert "defect-free" in html and "simulated world: filled" in html
    assert re.findall(r'data-missing="(\d+)"', html) == ["1", "0"]


def test_shot_html_of_a_fault_says_why() -> None:
    shot = _shot("fault") | {"fault": "DeviceError: camera <timeout>"}
    html = views.shot_html(shot, chain_positions())
    assert "DeviceError: camera &lt;timeout&gt;" in html and 'data-outcome="fault"' in html


def test_paper_column() -> None:
    assert views.paper_column(64, 1) == "1x64" and views.paper_column(1, 10) == "1x64"
    assert views.paper_column(16, 32) == "16x32" and views.paper_column(32, 64) == "32x64"
    assert views.paper_column(20, 20) == "16x32" and views.paper_column(64, 64) == "32x64"


def test_stage_rows_take_medians_beside_the_paper() -> None:
    shots = [_shot(), _shot() | {"cycles": [{"stage_us": {"I.acquire": 27_000.0, "III.solve": 9.0}}]}]
    rows = {r.stage: r for r in views.stage_rows(shots, "1x64")}
    assert list(rows) == list(STAGES)
    assert rows["I.acquire"].ours_ms == pytest.approx(25.5) and rows["I.acquire"].samples == 3
    assert rows["III.solve"].ours_ms == pytest.approx(0.007)
    assert rows["IV.upload"].ours_ms is None and rows["IV.upload"].paper_ms == PAPER_TABLE1_MS["1x64"]["IV.upload"]
    assert rows["IV.render"].paper_ms is None  # not a row of the paper's table
    html = views.timing_html(list(rows.values()), "1x64", shots=2)
    assert html.count("<tr data-stage=") == len(STAGES) and "exact 1D" in html and "25.5" in html


def test_history_series_rolling_success_and_cycles() -> None:
    shots = [{"shot_id": i, "outcome": "success" if i % 2 else "unsolvable", "rearrangements": i % 3} for i in range(6)]
    ids, rate, cycles = views.history_series(shots, window=2)
    assert ids.tolist() == [0, 1, 2, 3, 4, 5]
    assert rate.tolist() == [0.0, 50.0, 50.0, 50.0, 50.0, 50.0]
    assert cycles.tolist() == [0, 1, 2, 0, 1, 2]
    assert all(len(a) == 0 for a in views.history_series([]))


def test_frame_to_rgb_folds_a_chain_strip_and_keeps_grids() -> None:
    frame = np.full((16, 1024), 500, dtype=np.uint16)
    frame[8, 8::16] = 2000  # one bright pixel per trap
    rgb, note = views.frame_to_rgb(frame)
    assert rgb.dtype == np.uint8 and rgb.shape == (4 * 16 + 3, 256, 3)
    assert "4 strips of 256 px" in note
    assert (rgb[16] == 255).all()  # white gap between strips
    assert rgb[8, 8].sum() > rgb[0, 0].sum()  # the atom is brighter than the background
    big, note = views.frame_to_rgb(np.zeros((512, 2048), dtype=np.uint16))
    assert big.shape == (256, 1024, 3) and "every 2×2 px block" in note
    grown, _ = views.frame_to_rgb(frame, min_width=600)
    assert grown.shape[1] == 512
    flat, _ = views.frame_to_rgb(frame, fold=False)
    assert flat.shape == (16, 1024, 3)


def test_atom_points_in_pitch_units() -> None:
    points, colours, pitch = views.atom_points(["1100"], ["0110"], chain_positions(4))
    assert pitch == 16.0 and points[:, 0].tolist() == [0.5, 1.5, 2.5, 3.5] and (points[:, 1] == -0.5).all()
    assert [tuple(c) for c in colours] == [
        views._rgb(views.COLOURS[k]) for k in ("spare", "in_place", "missing", "empty")
    ]


def test_status_markdown() -> None:
    status = {
        "state": "fault", "reason": "DeviceError: AWG", "activity": None, "shots_done": 4, "successes": 3,
        "success_rate": 0.75, "truth_successes": 2, "config_name": "chain-1x64", "run_file": "runs/x.h5",
        "devices": {"camera": "sim", "awg": "sim", "time": "simulated"},
    }
    text = views.status_markdown(status)
    assert "FAULT" in text and "DeviceError: AWG" in text and "75 %" in text and "2/4" in text
    assert views.state_colour("fault") != views.state_colour("running")


@pytest.mark.parametrize("example", ["chain-1x64.yaml", "grid-16x32.yaml", "grid-32x64.yaml"])
def test_target_presets_are_valid_configurations(example: str) -> None:
    cfg = load_config(EXAMPLES / example)
    presets = target_presets(cfg)
    assert next(iter(presets)) == "as configured" and len(presets) >= 3
    for label, target in presets.items():
        data = cfg.model_dump(mode="json")
        data["target"] = {**data["target"], "count": None, "mask": None, **target}
        SystemConfig.model_validate(data)  # raises if a preset does not fit the array
