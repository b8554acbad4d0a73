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
    for target in presets.values():
        data = cfg.model_dump(mode="json")
        data["target"] = {**data["target"], "count": None, "mask": None, **target}
        SystemConfig.model_validate(data)  # raises if a preset does not fit the array


# -- the physicist's view: imaging histogram, per-trap maps, assembly, plans --------------------------------------


def test_counts_histogram_bins_every_sum() -> None:
    centres, hist = views.counts_histogram(np.array([0.0, 1.0, 1.0, 2.0, 10.0]), bins=5)
    assert hist.sum() == 5 and len(centres) == 5
    assert np.all(np.diff(centres) > 0)


def test_imaging_summary_finds_the_two_populations_and_the_error_of_each_threshold() -> None:
    rng = np.random.default_rng(1)
    counts = np.concatenate([rng.normal(100.0, 10.0, 3000), rng.normal(300.0, 20.0, 2000)])
    summary = views.imaging_summary(counts, current_threshold=150.0, candidate_threshold=110.0)
    fit = summary["fit"]
    assert fit["mean_empty"] == pytest.approx(100.0, abs=2.0)
    assert fit["mean_atom"] == pytest.approx(300.0, abs=3.0)
    assert fit["fraction_filled"] == pytest.approx(0.4, abs=0.02)
    # 150 is 5 sigma above the empty mean: a tiny error; 110 (1 sigma) misreads ~16 % of the empty 60 %
    assert summary["current"]["error"] < 1e-4
    assert summary["candidate"]["error"] == pytest.approx(0.6 * 0.1587, rel=0.15)
    assert summary["best"]["error"] <= summary["current"]["error"]
    # the curves drawn over the histogram hold about every sum
    centres, hist = views.counts_histogram(counts, bins=80)
    empty, atom = views.population_curves(centres, summary["fit"], int(hist.sum()))
    assert empty.sum() + atom.sum() == pytest.approx(hist.sum(), rel=0.05)
    assert centres[np.argmax(empty)] == pytest.approx(100.0, abs=10.0)


def test_imaging_summary_without_two_populations_says_so() -> None:
    summary = views.imaging_summary(np.full(100, 5.0), current_threshold=3.0)
    assert summary["fit"] is None and summary["current"] is None


def test_threshold_series_marks_the_bin_of_the_threshold() -> None:
    line = views.threshold_series(np.array([0.0, 1.0, 2.0, 3.0]), 7.0, 2.2)
    np.testing.assert_array_equal(line, [0.0, 0.0, 7.0, 0.0])
    assert not views.threshold_series(np.array([0.0, 1.0]), 7.0, None).any()


def test_heatmap_draws_each_trap_with_its_number_on_hover() -> None:
    positions = np.array([[8.0 + 16 * c, 8.0 + 16 * r] for r in range(2) for c in range(3)])
    values = np.array([[1.0, 0.5, np.nan], [0.0, 1.0, 1.0]])
    svg = views.heatmap_svg(values, positions, name="survival", samples=np.array([[4, 2, 0], [1, 3, 3]]))
    assert 'data-rows="2" data-cols="3"' in svg
    assert re.findall(r'data-value="([^"]+)"', svg) == ["1.000", "0.500", "—", "0.000", "1.000", "1.000"]
    assert "trap 3 (row 1, column 0): survival 0.000, 1 samples" in svg
    assert views.worst_traps(values, k=2) == [(3, 0.0), (1, 0.5)]


def test_assembly_series_from_shots() -> None:
    shots = [
        {"shot_id": 4, "outcome": "success", "cycles": [
            {"atoms": 10, "n_slots": 12, "n_steps": 20, "atoms_moved": 5, "t_image_ms": 21.0},
            {"atoms": 9, "n_slots": 3, "n_steps": 2, "atoms_moved": 1, "t_image_ms": 43.5},
            {"atoms": 9, "n_slots": 0, "n_steps": 0, "atoms_moved": 0, "t_image_ms": 65.0}]},
        {"shot_id": 5, "outcome": "unsolvable", "cycles": [
            {"atoms": 4, "n_slots": 0, "n_steps": 0, "t_image_ms": 21.0}]},
    ]
    a = views.assembly_series(shots)
    np.testing.assert_array_equal(a["shot_id"], [4, 5])
    np.testing.assert_array_equal(a["time_to_defect_free_ms"], [65.0, np.nan])
    np.testing.assert_array_equal(a["cycles"], [2, 0])
    np.testing.assert_array_equal(a["lost"], [1, 0])  # 10 -> 9 in the first cycle, 9 -> 9 in the second
    np.testing.assert_array_equal(a["slots"], [12, 3])
    np.testing.assert_array_equal(a["atoms_moved"], [5, 1])
    np.testing.assert_array_equal(a["cycle_shot"], [4, 4])
    np.testing.assert_array_equal(a["pickups"], [np.nan, np.nan])  # shots recorded before pick-ups were counted
    values, hist = views.cycles_histogram(a["cycles"])
    np.testing.assert_array_equal(values, [0, 1, 2])
    np.testing.assert_array_equal(hist, [1, 0, 1])


def test_losses_by_cause_and_pickups_per_rearrangement_cycle() -> None:
    """The lab's per-cycle report, aligned with the rearrangement cycles; a cycle without one (hardware) is NaN
    and leaves the means alone."""
    shots = [
        {"shot_id": 1, "outcome": "success", "cycles": [
            {"atoms": 10, "n_slots": 5, "pickups": 6, "truth": {"lost_by_cause": {"transfer": 2, "vacuum": 1}}},
            {"atoms": 7, "n_slots": 2, "pickups": 1, "truth": {"lost_by_cause": {"transfer": 0, "imaging": 1}}},
            {"atoms": 6, "n_slots": 0, "pickups": 0, "truth": {"lost_by_cause": {"imaging": 5}}}]},
        {"shot_id": 2, "outcome": "success", "cycles": [
            {"atoms": 9, "n_slots": 4, "pickups": None}, {"atoms": 9, "n_slots": 0}]},
    ]
    lost = views.losses_by_cause(shots)
    assert sorted(lost) == ["imaging", "transfer", "vacuum"]  # the last cycle planned nothing: not counted
    np.testing.assert_array_equal(lost["transfer"], [2, 0, np.nan])
    np.testing.assert_array_equal(lost["vacuum"], [1, 0, np.nan])
    np.testing.assert_array_equal(lost["imaging"], [0, 1, np.nan])
    np.testing.assert_array_equal(views.assembly_series(shots)["pickups"], [6, 1, np.nan])
    assembly = views.stats_report(
        None, shape=(2, 5), config_digest="d", threshold=None, candidate=None, shots=shots
    )["assembly"]
    assert assembly["pickups_per_cycle_mean"] == 3.5
    assert assembly["lost_by_cause_per_cycle_mean"] == {"transfer": 1.0, "vacuum": 0.5, "imaging": 0.5}
    html_text = views.assembly_html({
        "shots": 2, "success_rate": 1.0, "time_to_defect_free_ms_median": None, "lost_per_cycle_mean": 1.0,
        "slots_per_cycle_mean": 3.7, "atoms_moved_per_cycle_mean": 2.0, "pickups_per_cycle_mean": 3.5,
        "lost_by_cause_per_cycle_mean": {"transfer": 1.0, "vacuum": 0.5, "imaging": 0.5},
    })
    assert "3.5 pick-ups" in html_text
    assert html_text.index('data-cause="transfer"') < html_text.index('data-cause="vacuum"')  # biggest first


def test_plan_svg_draws_an_arrow_per_moved_atom() -> None:
    svg = views.plan_svg(["11001010"], ["00111100"], chain_positions(), np.array([[0, 2], [1, 3], [6, 5]]))
    assert svg.count('class="move"') == 3
    assert states(svg).count("spare") == 3
    assert views.plan_svg(["11001010"], ["00111100"], chain_positions(), None).count('class="move"') == 0


def grid_positions(ny: int, nx: int, *, transposed: bool = False) -> np.ndarray:
    """Trap centres (camera pixels, trap order row-major) of an ``ny`` x ``nx`` array 16 px apart; ``transposed``:
    a camera that sees the array's rows as picture columns."""
    r, c = np.divmod(np.arange(ny * nx), nx)
    x, y = (r, c) if transposed else (c, r)
    return np.stack([8.0 + 16.0 * x, 8.0 + 16.0 * y], axis=1)


def polylines(svg: str) -> list[str]:
    return re.findall(r'<polyline class="move path" points="([^"]+)"', svg)


def test_plan_svg_draws_an_interstitial_route_through_the_channels() -> None:
    """The atom at trap (0, 0) goes to (2, 2) as interstitial routing carries it: into the channel below row 0,
    along it to the channel between columns 1 and 2, down that one to row 2, onto the trap. Drawn as a
    polyline through those corners (22 px cells) ending in an arrow head, on the array's geometry as the
    camera sees it (rows as picture rows, or as picture columns)."""
    occupancy, target = ["1000", "0000", "0000"], ["0000", "0000", "0010"]
    route = np.array([[0, 0], [0.5, 0], [0.5, 1.5], [2, 1.5], [2, 2]])
    moves = np.array([[0, 10]])
    svg = views.plan_svg(occupancy, target, grid_positions(3, 4), moves, paths={0: route})
    assert polylines(svg) == ["11.0,11.0 11.0,22.0 44.0,22.0 44.0,55.0 55.0,55.0"]
    assert 'marker-end="url(#arrow-head)"' in svg and "<line " not in svg
    flipped = views.plan_svg(occupancy, target, grid_positions(3, 4, transposed=True), moves, paths={0: route})
    assert polylines(flipped) == ["11.0,11.0 22.0,11.0 22.0,44.0 55.0,44.0 55.0,55.0"]
    # a moved atom without a route (a run file written before routes were kept) keeps its straight arrow
    assert views.plan_svg(occupancy, target, grid_positions(3, 4), moves).count('<line class="move"') == 1


def test_plan_svg_draws_a_lattice_relay_atom_by_atom() -> None:
    """A relay on the chain: the atom at 1 steps to 2 and on to 3 while the one at 0 takes its place at 1 and
    the one at 6 goes to 5; each atom's own route, trap to trap (22 px cells on the chain of 8)."""
    svg = views.plan_svg(
        ["11000010"], ["01110000"], chain_positions(), np.array([[0, 1], [1, 3], [6, 5]]),
        paths={0: np.array([[0, 0], [0, 1]]), 1: np.array([[0, 1], [0, 3]]), 6: np.array([[0, 6], [0, 5]])},
    )
    assert polylines(svg) == ["11.0,11.0 33.0,11.0", "33.0,11.0 77.0,11.0", "143.0,11.0 121.0,11.0"]
    assert svg.count('class="move') == 3


def test_history_html_shows_a_recorded_cycle_with_its_losses_and_frame() -> None:
    """A historic shot's cycle as the run file gives it back: plan arrows, pick-ups, the lab's losses by cause
    (causes with none left out), whether a frame is kept; a cycle out of range shows the nearest one."""
    cycle = {"index": 0, "occupancy": ["11001010"], "atoms": 4, "defects": 2, "n_slots": 6, "stage_us": {},
             "moves": [[0, 2], [1, 3]], "pickups": 2, "frame": True,
             "truth": {"lost_by_cause": {"transfer": 1, "vacuum": 0, "released": 2}}}
    last = {"index": 1, "occupancy": ["00111100"], "atoms": 4, "defects": 0, "n_slots": 0, "stage_us": {},
            "moves": [], "pickups": None, "truth": {}}
    shot = {"shot_id": 9, "outcome": "success", "target": ["00111100"], "cycles": [cycle, last]}
    first = views.history_html(shot, 0, chain_positions(), download_url="/api/runs/x.h5")
    assert 'data-cycle="0"' in first and 'data-frame="1"' in first and 'data-lost="3"' in first
    assert "2 pick-ups" in first and "camera frame kept" in first
    assert re.findall(r'data-cause="(\w+)"', first) == ["transfer", "released"]
    assert first.count('class="move"') == 2 and 'data-paths="0"' in first  # no routes recorded: arrows
    cycle["paths"] = [{"source": 0, "points": [[0, 0], [0, 2]]}, {"source": 1, "points": [[0, 1], [0, 3]]}]
    routed = views.history_html(shot, 0, chain_positions(), download_url="/api/runs/x.h5")
    assert 'data-paths="2"' in routed and len(polylines(routed)) == 2 and 'class="move"' not in routed
    assert views.clamp_cycle(shot, 7) == 1 and views.clamp_cycle(shot, -1) == 0
    beyond = views.history_html(shot, 7, chain_positions(), download_url="/api/runs/x.h5")
    assert 'data-cycle="1"' in beyond and 'data-frame="0"' in beyond and 'data-lost=""' in beyond
    assert "lost after this image" not in beyond and "pick-ups" not in beyond
