"""What the dashboard shows, as plain functions of plain data (tested without viser).

Inputs are the JSON shapes of the API: a shot is ``ShotRecord.to_dict()`` (what ``GET /api/shots/{id}``
returns), a status is ``StatusOut.model_dump()``. Outputs are strings (HTML/SVG, markdown) and numpy arrays
(images, plot series) that ``frontend.dashboard`` hands to viser unchanged.

The atom map draws every trap where the camera sees it (the configured trap pixel positions), so the map and
the camera image have the same orientation, and colours each trap by what a person needs at a glance:

- green disc: a target trap holding an atom (in place);
- red ring on pink: a target trap that is empty (missing: what the next cycle must fill);
- blue disc: an atom outside the target (a spare, available to fill a hole);
- small grey dot: an empty trap outside the target.
"""

from __future__ import annotations

import html
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from engine.imaging_calibration import Population, calibrate_threshold, error_probability
from engine.timing import PAPER_TABLE1_MS, STAGES
from engine.trap_stats import TrapStatistics

__all__ = [
    "COLOURS",
    "StageRow",
    "assembly_html",
    "assembly_series",
    "atom_map_svg",
    "atom_points",
    "candidate_threshold",
    "counts_histogram",
    "cycles_histogram",
    "frame_to_rgb",
    "heatmap_svg",
    "history_html",
    "history_series",
    "imaging_html",
    "imaging_summary",
    "lab_stats",
    "plan_svg",
    "route_points_px",
    "population_curves",
    "threshold_series",
    "worst_traps",
    "paper_column",
    "shot_html",
    "stage_rows",
    "stats_report",
    "state_colour",
    "status_markdown",
    "timing_html",
    "trap_layout",
]

COLOURS = {
    "in_place": "#2ca02c",
    "missing": "#d62728",
    "missing_fill": "#fde0e0",
    "spare": "#4c78c8",
    "empty": "#c8c8c8",
    "target_bg": "#e6f4e6",
    "ours": "#4c78c8",
    "paper": "#b0b0b0",
}

_PAPER_PROBLEM = {"1x64": "exact 1D, 1×64 traps", "16x32": "red-rec, 16×32 traps", "32x64": "red-rec, 32×64 traps"}


# -- atom map ---------------------------------------------------------------------------------------------------


def trap_layout(positions_xy: np.ndarray) -> tuple[np.ndarray, int, int]:
    """Trap positions (camera pixels, ``float[n, 2]``) -> integer grid cells ``int[n, 2]`` (column, row of the
    picture) and the picture's size in cells ``(n_across, n_down)``. The pitch is the smallest distance
    between two traps along each picture axis."""
    xy = np.asarray(positions_xy, dtype=np.float64)
    cells = np.zeros(xy.shape, dtype=np.int64)
    for axis in (0, 1):
        v = xy[:, axis]
        distinct = np.unique(np.round(v, 3))
        steps = np.diff(distinct)
        pitch = steps[steps > 1e-6].min() if np.any(steps > 1e-6) else 1.0
        cells[:, axis] = np.round((v - v.min()) / pitch).astype(np.int64)
    return cells, int(cells[:, 0].max()) + 1, int(cells[:, 1].max()) + 1


def _bits(rows: Sequence[str]) -> np.ndarray:
    return np.array([[c == "1" for c in row] for row in rows], dtype=bool).ravel()


def atom_map_svg(
    occupancy: Sequence[str],
    target: Sequence[str],
    positions_xy: np.ndarray,
    *,
    max_width_px: float = 720,
    max_cell_px: float = 22,
    title: str | None = None,
) -> str:
    """One picture of the array: ``occupancy``/``target`` are rows of '0'/'1' (flat order = trap order of
    ``positions_xy``). Returns an inline ``<svg>`` whose traps carry ``data-state`` (in_place, missing,
    spare, empty) so that tests and people can count them."""
    occ, tgt = _bits(occupancy), _bits(target)
    cells, across, down = trap_layout(positions_xy)
    if occ.size != cells.shape[0] or tgt.size != cells.shape[0]:
        raise ValueError(f"{occ.size} occupancies and {tgt.size} target bits for {cells.shape[0]} traps")
    cell = max(3.0, min(max_cell_px, max_width_px / across))
    r = 0.38 * cell
    width, height = across * cell, down * cell
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" class="atom-map" width="{width:.0f}" height="{height:.0f}" '
        f'viewBox="0 0 {width:.1f} {height:.1f}" role="img">'
    ]
    if title:
        parts.append(f"<title>{html.escape(title)}</title>")
    for (cx, cy), t in zip(cells, tgt, strict=True):
        if t:
            parts.append(
                f'<rect x="{cx * cell:.1f}" y="{cy * cell:.1f}" width="{cell:.1f}" height="{cell:.1f}" '
                f'fill="{COLOURS["target_bg"]}"/>'
            )
    stroke = max(1.0, 0.14 * cell)
    for (cx, cy), o, t in zip(cells, occ, tgt, strict=True):
        x, y = (cx + 0.5) * cell, (cy + 0.5) * cell
        if o and t:
            parts.append(
                f'<circle data-state="in_place" cx="{x:.1f}" cy="{y:.1f}" r="{r:.1f}" fill="{COLOURS["in_place"]}"/>'
            )
        elif t:
            parts.append(
                f'<circle data-state="missing" cx="{x:.1f}" cy="{y:.1f}" r="{r - stroke / 2:.1f}" '
                f'fill="{COLOURS["missing_fill"]}" stroke="{COLOURS["missing"]}" stroke-width="{stroke:.1f}"/>'
            )
        elif o:
            parts.append(
                f'<circle data-state="spare" cx="{x:.1f}" cy="{y:.1f}" r="{r:.1f}" fill="{COLOURS["spare"]}"/>'
            )
        else:
            parts.append(
                f'<circle data-state="empty" cx="{x:.1f}" cy="{y:.1f}" r="{max(1.0, 0.14 * cell):.1f}" '
                f'fill="{COLOURS["empty"]}"/>'
            )
    parts.append("</svg>")
    return "".join(parts)


def _rgb(hex_colour: str) -> tuple[int, int, int]:
    return int(hex_colour[1:3], 16), int(hex_colour[3:5], 16), int(hex_colour[5:7], 16)


def atom_points(
    occupancy: Sequence[str], target: Sequence[str], positions_xy: np.ndarray
) -> tuple[np.ndarray, np.ndarray, float]:
    """The atom map for the 3D view: ``(points float32[n, 3], colours uint8[n, 3], pitch)``.

    Points are in units of the trap pitch (camera pixels / ``pitch``), x to the right and y up (the camera's
    rows run down, so y is negated); colours follow the atom map's states."""
    occ, tgt = _bits(occupancy), _bits(target)
    xy = np.asarray(positions_xy, dtype=np.float64)
    d = np.diff(np.unique(np.round(xy, 3).ravel()))
    steps = [np.min(np.abs(np.diff(np.unique(np.round(xy[:, a], 3))))) for a in (0, 1) if np.unique(xy[:, a]).size > 1]
    pitch = float(min(steps)) if steps else float(d[d > 0].min()) if np.any(d > 0) else 1.0
    points = np.zeros((xy.shape[0], 3), dtype=np.float32)
    points[:, 0] = xy[:, 0] / pitch
    points[:, 1] = -xy[:, 1] / pitch
    state = np.where(occ & tgt, 0, np.where(tgt, 1, np.where(occ, 2, 3)))
    palette = np.array(
        [_rgb(COLOURS["in_place"]), _rgb(COLOURS["missing"]), _rgb(COLOURS["spare"]), _rgb(COLOURS["empty"])],
        dtype=np.uint8,
    )
    return points, palette[state], pitch


def _legend() -> str:
    def item(colour: str, label: str, ring: bool = False) -> str:
        style = (
            f"background:{COLOURS['missing_fill']};border:2px solid {colour}"
            if ring
            else f"background:{colour}"
        )
        return (
            f'<span style="display:inline-flex;align-items:center;margin-right:10px">'
            f'<span style="display:inline-block;width:10px;height:10px;border-radius:50%;{style};'
            f'margin-right:4px"></span>{label}</span>'
        )

    return (
        '<div style="font-size:11px;color:#555;margin:2px 0 6px 0">'
        + item(COLOURS["in_place"], "atom in target")
        + item(COLOURS["missing"], "missing (target empty)", ring=True)
        + item(COLOURS["spare"], "spare atom")
        + item(COLOURS["empty"], "empty trap")
        + "</div>"
    )


_OUTCOME_STYLE = {
    "success": ("#2ca02c", "defect-free"),
    "unsolvable": ("#ff7f0e", "unsolvable (too few atoms)"),
    "max_cycles": ("#ff7f0e", "gave up after max cycles"),
    "fault": ("#d62728", "fault"),
}


def shot_html(shot: Mapping[str, Any], positions_xy: np.ndarray, *, width_px: float = 720) -> str:
    """A finished shot: outcome, then the atom map before each cycle and after the last one.

    Cycle ``k``'s image is what the camera saw before rearrangement ``k``; the last image is the final state.
    Chains (one picture row) stack every cycle; 2D arrays show the first and last images side by side and the
    ones in between below them, smaller.
    """
    cycles = list(shot["cycles"])
    target = shot["target"]
    colour, words = _OUTCOME_STYLE.get(shot["outcome"], ("#555", shot["outcome"]))
    n_target = sum(row.count("1") for row in target)
    rearrangements = sum(1 for c in cycles if c.get("n_slots", 0) > 0)
    truth = shot.get("truth", {}).get("target_filled")
    truth_txt = "" if truth is None else f" · simulated world: {'filled' if truth else 'NOT filled'}"
    fault = f" — {html.escape(str(shot['fault']))}" if shot.get("fault") else ""
    head = (
        f'<div style="font-size:13px;margin-bottom:2px"><b>Shot {int(shot["shot_id"])}</b> '
        f'<span style="background:{colour};color:white;border-radius:3px;padding:0 5px">{html.escape(words)}</span>'
        f"{fault} · {rearrangements} rearrangement cycle{'s' if rearrangements != 1 else ''} · "
        f"target {n_target} traps{truth_txt}</div>"
    )
    _, across, down = trap_layout(positions_xy)
    two_d = down > 1
    panels = []
    for i, c in enumerate(cycles):
        last = i == len(cycles) - 1
        if last and len(cycles) > 1:
            label = f"final image (after {i} rearrangement{'s' if i != 1 else ''})"
        elif i == 0:
            label = "loaded (before rearranging)" if not last else "loaded (final: nothing to move)"
        else:
            label = f"after rearrangement {i}"
        missing, atoms = int(c["defects"]), int(c["atoms"])
        status = (
            f'<span style="color:{COLOURS["in_place"]}">all {n_target} in place</span>'
            if missing == 0
            else f'<span style="color:{COLOURS["missing"]}">{missing} missing</span>'
        )
        small = two_d and 0 < i < len(cycles) - 1
        map_width = width_px if not two_d else (width_px / 2 - 12 if not small else width_px / 3 - 12)
        svg = atom_map_svg(c["occupancy"], target, positions_xy, max_width_px=map_width, title=label)
        panels.append(
            f'<div class="cycle" data-cycle="{i}" data-missing="{missing}" style="margin:0 10px 6px 0">'
            f'<div style="font-size:11px;color:#333">{html.escape(label)}: {atoms} atoms, {status}</div>{svg}</div>'
        )
    layout = "display:flex;flex-wrap:wrap;align-items:flex-start" if two_d else "display:block"
    return (
        f'<div id="atom-map" data-shot-id="{int(shot["shot_id"])}" data-outcome="{html.escape(shot["outcome"])}" '
        f'data-cycles="{len(cycles)}">{head}{_legend()}<div style="{layout}">{"".join(panels)}</div></div>'
    )


# -- timing -----------------------------------------------------------------------------------------------------


def paper_column(nx: int, ny: int) -> str:
    """The paper's Table 1 problem closest to an ``nx`` x ``ny`` array (a chain maps to 1x64)."""
    if nx == 1 or ny == 1:
        return "1x64"
    n = nx * ny
    return min(("16x32", "32x64"), key=lambda k: abs(math.log(n / (int(k.split("x")[0]) * int(k.split("x")[1])))))


@dataclass(frozen=True)
class StageRow:
    stage: str
    ours_ms: float | None  # median over the cycles that ran the stage
    paper_ms: float | None
    samples: int


def stage_rows(shots: Sequence[Mapping[str, Any]], column: str) -> list[StageRow]:
    """Per stage, the median time (ms) over every cycle of ``shots`` that ran it, beside the paper's value."""
    samples: dict[str, list[float]] = {s: [] for s in STAGES}
    for shot in shots:
        for cycle in shot["cycles"]:
            for stage, us in cycle.get("stage_us", {}).items():
                if stage in samples and us is not None and math.isfinite(us):
                    samples[stage].append(us / 1e3)
    paper = PAPER_TABLE1_MS.get(column, {})
    return [
        StageRow(s, float(np.median(v)) if v else None, paper.get(s), len(v))
        for s, v in samples.items()
    ]


def _bar(ms: float | None, colour: str) -> str:
    """A horizontal bar on a log scale from 1 us (0 %) to 100 ms (100 %)."""
    if ms is None or ms <= 0:
        return ""
    pct = min(100.0, max(1.0, (math.log10(ms) + 3) / 5 * 100))
    return f'<div style="height:6px;width:{pct:.1f}%;background:{colour};margin:1px 0"></div>'


def _fmt_ms(ms: float | None) -> str:
    if ms is None:
        return "—"
    return f"{ms:.3f}" if ms < 10 else f"{ms:.1f}"


def timing_html(rows: Sequence[StageRow], column: str, *, shots: int) -> str:
    """A table: stage, our median, the paper's value, and both as bars on one log scale."""
    body = []
    ours_total = sum(r.ours_ms for r in rows if r.ours_ms is not None)
    paper_total = sum(r.paper_ms for r in rows if r.paper_ms is not None)
    for r in rows:
        body.append(
            f'<tr data-stage="{r.stage}"><td style="white-space:nowrap">{r.stage}</td>'
            f'<td style="text-align:right">{_fmt_ms(r.ours_ms)}</td><td style="text-align:right;color:#777">'
            f"{_fmt_ms(r.paper_ms)}</td><td style=\"width:45%\">{_bar(r.ours_ms, COLOURS['ours'])}"
            f"{_bar(r.paper_ms, COLOURS['paper'])}</td></tr>"
        )
    body.append(
        f'<tr style="border-top:1px solid #ccc"><td><b>cycle</b></td><td style="text-align:right"><b>'
        f"{_fmt_ms(ours_total if shots else None)}</b></td><td style=\"text-align:right;color:#777\">"
        f"{_fmt_ms(paper_total or None)}</td><td></td></tr>"
    )
    return (
        '<div id="timing" style="font-size:11px">'
        f'<div style="margin-bottom:3px">Median per stage (ms) over the last {shots} shot{"s" if shots != 1 else ""}'
        f" (stages III–V: rearranging cycles only) vs the paper's Table 1 ({_PAPER_PROBLEM.get(column, column)})."
        f' Bars: log scale 1 µs – 100 ms, <span style="color:{COLOURS["ours"]}">■ this lab</span> '
        f'<span style="color:{COLOURS["paper"]}">■ paper</span>.</div>'
        '<table style="width:100%;border-collapse:collapse"><tr style="color:#555"><th align="left">stage</th>'
        '<th align="right">here</th><th align="right">paper</th><th></th></tr>'
        + "".join(body)
        + "</table></div>"
    )


# -- history ----------------------------------------------------------------------------------------------------


def history_series(
    shots: Sequence[Mapping[str, Any]], *, window: int = 20
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(shot_id, success rate in % over the last `window` shots, rearrangement cycles)`` in shot order."""
    if not shots:
        empty = np.zeros(0)
        return empty, empty, empty
    ids = np.array([s["shot_id"] for s in shots], dtype=np.float64)
    ok = np.array([s["outcome"] == "success" for s in shots], dtype=np.float64)
    cycles = np.array(
        [s["rearrangements"] if "rearrangements" in s else sum(1 for c in s["cycles"] if c.get("n_slots", 0) > 0)
         for s in shots],
        dtype=np.float64,
    )
    csum = np.concatenate([[0.0], np.cumsum(ok)])
    idx = np.arange(1, len(ok) + 1)
    lo = np.maximum(0, idx - window)
    rate = 100.0 * (csum[idx] - csum[lo]) / (idx - lo)
    return ids, rate, cycles


# -- status -----------------------------------------------------------------------------------------------------

_STATE_COLOUR = {"idle": "#777777", "armed": "#9467bd", "running": "#2ca02c", "fault": "#d62728"}


def status_markdown(status: Mapping[str, Any]) -> str:
    """The status line block: state (and why), what runs, success so far."""
    state = status["state"]
    lines = [f"**State: {state.upper()}**" + (f" — {status['activity']}" if status.get("activity") else "")]
    if status.get("reason"):
        lines.append(f"Fault: `{status['reason']}`")
    done = status["shots_done"]
    if done:
        rate = status.get("success_rate") or 0.0
        truth = status.get("truth_successes")
        world = f" (simulated world: {truth}/{done})" if truth is not None else ""
        lines.append(f"Shots: {done}, defect-free {status['successes']} = {100 * rate:.0f} %{world}")
    else:
        lines.append("Shots: none yet")
    dev = status["devices"]
    lines.append(f"Config `{status['config_name']}` · camera {dev['camera']}, AWG {dev['awg']} ({dev['time']})")
    if status.get("run_file"):
        lines.append(f"Run file `{status['run_file']}`")
    return "  \n".join(lines)


def state_colour(state: str) -> str:
    return _STATE_COLOUR.get(state, "#777777")


# -- camera image -----------------------------------------------------------------------------------------------

_LUT_ANCHORS = np.array(
    [[0, 0, 4], [40, 11, 84], [101, 21, 110], [159, 42, 99], [212, 72, 66], [245, 125, 21], [250, 193, 39],
     [252, 255, 164]],
    dtype=np.float64,
)  # an 'inferno'-like ramp


def _lut() -> np.ndarray:
    x = np.linspace(0, len(_LUT_ANCHORS) - 1, 256)
    lo = np.floor(x).astype(int).clip(0, len(_LUT_ANCHORS) - 2)
    f = (x - lo)[:, None]
    return ((1 - f) * _LUT_ANCHORS[lo] + f * _LUT_ANCHORS[lo + 1]).round().astype(np.uint8)


_LUT = _lut()


def _fold(frame: np.ndarray, *, target_aspect: float = 3.0) -> tuple[np.ndarray, int]:
    """Cut a very wide frame into ``k`` equal strips stacked top to bottom (aspect closest to ``target_aspect``)."""
    h, w = frame.shape
    best = min(
        (k for k in range(1, 17) if w % k == 0),
        key=lambda k: abs(math.log((w / k) / (h * k + (k - 1)) / target_aspect)),
    )
    if best == 1:
        return frame, 1
    strips = frame.reshape(h, best, w // best).transpose(1, 0, 2)
    gap = np.full((best, 1, w // best), np.nan)
    return np.concatenate([strips, gap], axis=1).reshape(best * (h + 1), w // best)[:-1], best


def frame_to_rgb(
    frame: np.ndarray, *, max_side: int = 1024, fold: bool = True, min_width: int = 0
) -> tuple[np.ndarray, str]:
    """A camera frame (raw counts) as an RGB picture for people, and a note on how it was drawn.

    Counts are scaled between the 1st and 99.8th percentile (the background and the brightest atoms) with a
    square-root stretch; very wide strips (a chain's 16 x 1024 ROI) are folded into stacked strips so the
    atoms stay visible (unless ``fold`` is false); large frames are downsampled by whole factors to at most
    ``max_side`` pixels, small ones enlarged by whole factors to at least ``min_width`` pixels.
    """
    img = np.asarray(frame, dtype=np.float64)
    lo, hi = np.percentile(img, [1.0, 99.8])
    hi = max(hi, lo + 1.0)
    scaled = np.sqrt(np.clip((img - lo) / (hi - lo), 0.0, 1.0))
    folded, k = _fold(scaled) if fold else (scaled, 1)
    step = max(1, math.ceil(max(folded.shape) / max_side))
    if step > 1:
        h, w = (folded.shape[0] // step) * step, (folded.shape[1] // step) * step
        folded = np.nanmax(folded[:h, :w].reshape(h // step, step, w // step, step), axis=(1, 3))
    gap = np.isnan(folded)
    rgb = _LUT[np.nan_to_num(folded * 255, nan=0).astype(np.uint8)]
    rgb[gap] = 255
    grow = max(1, min_width // rgb.shape[1]) if step == 1 else 1
    if grow > 1:
        rgb = rgb.repeat(grow, axis=0).repeat(grow, axis=1)
    h, w = frame.shape
    note = f"{w}×{h} px, counts {lo:.0f}–{hi:.0f}"
    if k > 1:
        note += f", shown as {k} strips of {w // k} px (left to right, top to bottom)"
    if step > 1:
        note += f", every {step}×{step} px block shown by its brightest pixel"
    return np.ascontiguousarray(rgb), note


# -- imaging: the histogram of weighted sums, its two populations and the thresholds ---------------------------


def counts_histogram(counts: np.ndarray, *, bins: int = 60) -> tuple[np.ndarray, np.ndarray]:
    """``(bin centres, counts per bin)`` of PSF-weighted sums, over their 0.1-99.9th percentile range."""
    x = np.asarray(counts, dtype=np.float64).ravel()
    x = x[np.isfinite(x)]
    if x.size == 0:
        return np.zeros(0), np.zeros(0)
    lo, hi = np.percentile(x, [0.1, 99.9])
    hi = max(hi, lo + 1.0)
    hist, edges = np.histogram(np.clip(x, lo, hi), bins=bins, range=(lo, hi))
    return 0.5 * (edges[:-1] + edges[1:]), hist.astype(np.float64)


def _populations(fit: Mapping[str, float]) -> tuple[Population, Population]:
    """The empty and the one-atom population of a fit (``imaging_summary(...)["fit"]``)."""

    def population(kind: str) -> Population:
        return Population(*(np.asarray(fit[f"{m}_{kind}"], dtype=np.float64) for m in ("mean", "std", "skew")))

    return population("empty"), population("atom")


def _threshold_row(fit: Mapping[str, float], threshold: float | None) -> dict[str, float | None]:
    """A threshold and the detection error the fitted populations imply for it (``None``s if no threshold)."""
    if threshold is None:
        return {"threshold": None, "error": None}
    empty, atom = _populations(fit)
    error = error_probability(np.asarray(threshold, dtype=np.float64), empty, atom, fit["fraction_filled"])
    return {"threshold": float(threshold), "error": float(error)}


#: The most sums a histogram fit uses (an evenly spaced subset beyond): 64x128 traps x 50 shots are 400,000,
#: and the fit's cost grows with them while its precision stops mattering long before.
FIT_SAMPLES = 40_000


def _fit_sample(counts: np.ndarray) -> np.ndarray:
    x = np.asarray(counts, dtype=np.float64).ravel()
    x = x[np.isfinite(x)]
    return x[:: max(1, math.ceil(x.size / FIT_SAMPLES))]


def imaging_summary(
    counts: np.ndarray, *, current_threshold: float | None, candidate_threshold: float | None = None
) -> dict[str, Any]:
    """The two populations fitted to ``counts`` (empty / one atom, as a calibration fits them; at most
    ``FIT_SAMPLES`` of them) and, for the threshold in use and for a calibration's candidate, the detection
    error that fit implies.

    ``fit`` is ``None`` when the sums do not split into two populations (too few, or an empty or full array).
    ``best`` is the fit's own minimum-error threshold."""
    x = np.asarray(counts, dtype=np.float64).ravel()
    try:
        fit = calibrate_threshold(_fit_sample(x))
    except ValueError:
        return {"samples": int(x.size), "fit": None, "best": None, "current": None, "candidate": None}
    populations = {
        "mean_empty": fit.mean_empty, "std_empty": fit.std_empty, "skew_empty": fit.skew_empty,
        "mean_atom": fit.mean_atom, "std_atom": fit.std_atom, "skew_atom": fit.skew_atom,
        "fraction_filled": fit.fraction_filled, "separation": fit.separation,
    }
    return {
        "samples": int(x.size),
        "fit": populations,
        "best": _threshold_row(populations, fit.threshold),
        "current": _threshold_row(populations, current_threshold),
        "candidate": _threshold_row(populations, candidate_threshold),
    }


def population_curves(
    centres: np.ndarray, fit: Mapping[str, float] | None, samples: int
) -> tuple[np.ndarray, np.ndarray]:
    """The two fitted populations (``imaging_summary(...)["fit"]``) as expected sums per histogram bin at
    ``centres`` for a histogram of ``samples`` sums (zeros if there is no fit)."""
    zero = np.zeros(len(centres))
    if fit is None or len(centres) < 2:
        return zero, zero
    empty, atom = _populations(fit)
    width = float(centres[1] - centres[0])
    c = np.asarray(centres, dtype=np.float64)
    p = fit["fraction_filled"]
    return (
        samples * (1 - p) * width * np.exp(empty.logpdf(c)),
        samples * p * width * np.exp(atom.logpdf(c)),
    )


def threshold_series(centres: np.ndarray, height: float, threshold: float | None) -> np.ndarray:
    """A marker for a uPlot series on the histogram's x values: a spike of ``height`` in the bin holding the
    threshold, 0 elsewhere (no NaN: viser hands uPlot typed arrays, and one NaN blanks the whole plot)."""
    line = np.zeros(len(centres))
    if threshold is not None and len(centres):
        line[int(np.argmin(np.abs(np.asarray(centres) - threshold)))] = height
    return line


# -- per-trap maps ----------------------------------------------------------------------------------------------


def _heat_colour(value: float) -> str:
    """0 -> red, 0.5 -> yellow, 1 -> green (NaN: grey)."""
    if not math.isfinite(value):
        return "#dddddd"
    v = min(1.0, max(0.0, value))
    r = 215 if v < 0.5 else int(215 - (v - 0.5) * 2 * (215 - 44))
    g = int(40 + v * 2 * (190 - 40)) if v < 0.5 else int(190 - (v - 0.5) * 2 * (190 - 160))
    return f"#{r:02x}{g:02x}{40:02x}"


def heatmap_svg(
    values: np.ndarray, positions_xy: np.ndarray, *, name: str, samples: np.ndarray | None = None,
    max_width_px: float = 340, max_cell_px: float = 16,
) -> str:
    """One statistic per trap (``float[ny, nx]`` in [0, 1], NaN: no data) drawn where the camera sees each trap;
    every cell carries a ``<title>`` (hover: trap, row, column, value and samples) and ``data-value``."""
    v = np.asarray(values, dtype=np.float64)
    ny, nx = v.shape
    cells, across, down = trap_layout(positions_xy)
    if cells.shape[0] != v.size:
        raise ValueError(f"{v.size} values for {cells.shape[0]} traps")
    cell = max(2.0, min(max_cell_px, max_width_px / across))
    width, height = across * cell, down * cell
    flat = v.ravel()
    n_samples = None if samples is None else np.asarray(samples).ravel()
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" class="heatmap" data-name="{html.escape(name)}" '
        f'data-rows="{ny}" data-cols="{nx}" width="{width:.0f}" height="{height:.0f}" '
        f'viewBox="0 0 {width:.1f} {height:.1f}">'
    ]
    for t, ((cx, cy), value) in enumerate(zip(cells, flat, strict=True)):
        shown = "—" if not math.isfinite(value) else f"{value:.3f}"
        extra = "" if n_samples is None else f", {int(n_samples[t])} samples"
        parts.append(
            f'<rect x="{cx * cell:.1f}" y="{cy * cell:.1f}" width="{cell:.1f}" height="{cell:.1f}" '
            f'fill="{_heat_colour(value)}" data-value="{shown}"><title>trap {t} (row {t // nx}, column {t % nx}): '
            f"{html.escape(name)} {shown}{extra}</title></rect>"
        )
    parts.append("</svg>")
    return "".join(parts)


def worst_traps(values: np.ndarray, *, k: int = 3) -> list[tuple[int, float]]:
    """The ``k`` traps with the lowest value (NaN skipped): ``(flat index, value)``, lowest first."""
    flat = np.asarray(values, dtype=np.float64).ravel()
    order = [int(i) for i in np.argsort(np.where(np.isfinite(flat), flat, np.inf)) if math.isfinite(flat[i])]
    return [(i, float(flat[i])) for i in order[:k]]


# -- assembly ---------------------------------------------------------------------------------------------------


def _rearranging_cycles(shots: Sequence[Mapping[str, Any]]) -> Iterator[tuple[Mapping[str, Any], ...]]:
    """``(shot, cycle, next cycle)`` for every cycle that played a plan and was followed by an image."""
    for shot in shots:
        cycles = shot["cycles"]
        for before, after in zip(cycles, cycles[1:], strict=False):
            if before.get("n_slots", 0) > 0:
                yield shot, before, after


def assembly_series(shots: Sequence[Mapping[str, Any]]) -> dict[str, np.ndarray]:
    """Assembly figures from shot dicts (``ShotRecord.to_dict()``), oldest first.

    Per shot: ``shot_id``, ``time_to_defect_free_ms`` (when the image showing the defect-free array was in
    memory, NaN for a shot that did not end defect-free), ``cycles`` (rearrangement cycles). Per rearrangement
    cycle: ``cycle_shot`` (its shot id), ``lost`` (atoms the next image is missing: atoms before minus after,
    the observed loss of that cycle whatever its cause), ``slots``, ``steps``, ``atoms_moved`` and ``pickups``
    (NaN where not known)."""
    ids, ttd, n_cycles = [], [], []
    for shot in shots:
        cycles = shot["cycles"]
        ids.append(shot["shot_id"])
        ok = shot["outcome"] == "success" and cycles
        ttd.append(float(cycles[-1].get("t_image_ms", np.nan)) if ok else np.nan)
        n_cycles.append(sum(1 for c in cycles if c.get("n_slots", 0) > 0))
    cycle_shot, lost, slots, steps, moved, pickups = [], [], [], [], [], []
    for shot, before, after in _rearranging_cycles(shots):
        cycle_shot.append(shot["shot_id"])
        lost.append(int(before["atoms"]) - int(after["atoms"]))
        slots.append(before["n_slots"])
        steps.append(before.get("n_steps", 0))
        moved.append(before.get("atoms_moved", 0))
        picked = before.get("pickups")
        pickups.append(np.nan if picked is None else picked)
    f = np.float64
    return {
        "shot_id": np.array(ids, dtype=f), "time_to_defect_free_ms": np.array(ttd, dtype=f),
        "cycles": np.array(n_cycles, dtype=f), "cycle_shot": np.array(cycle_shot, dtype=f),
        "lost": np.array(lost, dtype=f), "slots": np.array(slots, dtype=f), "steps": np.array(steps, dtype=f),
        "atoms_moved": np.array(moved, dtype=f), "pickups": np.array(pickups, dtype=f),
    }


def losses_by_cause(shots: Sequence[Mapping[str, Any]]) -> dict[str, np.ndarray]:
    """Atoms the lab saw lost in each rearrangement cycle (the cycles of ``assembly_series``), per cause: from
    the cycles' ``truth.lost_by_cause`` (the simulated world knows why atoms go; hardware does not, and then
    this is empty). NaN for a cycle without a report."""
    reports = [before.get("truth", {}).get("lost_by_cause") for _, before, _ in _rearranging_cycles(shots)]
    causes = sorted({cause for report in reports if report for cause in report})
    return {
        cause: np.array([np.nan if not r else r.get(cause, 0) for r in reports], dtype=np.float64) for cause in causes
    }


def _nanmean(values: np.ndarray) -> float | None:
    """The mean of the known (finite) values; None where there are none."""
    known = values[np.isfinite(values)]
    return float(known.mean()) if known.size else None


def cycles_histogram(cycles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(0..max, shots with that many rearrangement cycles)``."""
    c = np.asarray(cycles, dtype=np.int64)
    if c.size == 0:
        return np.zeros(1), np.zeros(1)
    hist = np.bincount(c)
    return np.arange(hist.size, dtype=np.float64), hist.astype(np.float64)


# -- history: a recorded cycle with its plan drawn as arrows ----------------------------------------------------


def route_points_px(points: np.ndarray, cells: np.ndarray, nx: int, cell_px: float) -> np.ndarray:
    """Corner points of a route (``float[m, 2]``: row, column in sites; halves are channels between traps) ->
    picture pixels ``float[m, 2]`` (x, y). A point between traps is the mean of the cells of the traps around
    it, so a route is drawn on whatever grid the traps sit (a camera that flips or swaps the array's axes)."""
    yx = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    out = np.zeros_like(yx)
    for lo_y, lo_x in ((np.floor, np.floor), (np.floor, np.ceil), (np.ceil, np.floor), (np.ceil, np.ceil)):
        out += cells[lo_y(yx[:, 0]).astype(np.int64) * nx + lo_x(yx[:, 1]).astype(np.int64)]
    return (out / 4 + 0.5) * cell_px


def plan_svg(
    occupancy: Sequence[str], target: Sequence[str], positions_xy: np.ndarray, moves: np.ndarray | None,
    *, paths: Mapping[int, np.ndarray] | None = None, max_width_px: float = 720, title: str | None = None,
) -> str:
    """The atom map of one cycle with its plan over it: each moved atom's route (``paths``: source trap ->
    ``float[m, 2]`` corner points, row and column in sites, ``3.5`` a channel) as a polyline with an arrow head
    where it ends, so a route through the channels or a lattice relay shows as the atoms travelled; a moved atom
    without a route (``moves``: ``int[k, 2]`` source, destination; older run files) as a straight arrow."""
    cells, across, _ = trap_layout(positions_xy)
    svg = atom_map_svg(occupancy, target, positions_xy, max_width_px=max_width_px, title=title)
    if moves is None or len(moves) == 0:
        return svg
    cell = max(3.0, min(22.0, max_width_px / across))
    style = f'stroke="#333" stroke-width="{max(0.8, 0.08 * cell):.1f}" marker-end="url(#arrow-head)"'
    arrows = [
        '<defs><marker id="arrow-head" viewBox="0 0 10 10" refX="9" refY="5" markerWidth="4" markerHeight="4" '
        'orient="auto-start-reverse"><path d="M0,0 L10,5 L0,10 z" fill="#333"/></marker></defs>'
    ]
    paths = paths or {}
    nx = len(occupancy[0])
    for src, dst in np.asarray(moves, dtype=np.int64):
        route = paths.get(int(src))
        if route is not None and len(route) >= 2:
            xy = route_points_px(route, cells, nx, cell)
            points = " ".join(f"{x:.1f},{y:.1f}" for x, y in xy)
            arrows.append(f'<polyline class="move path" points="{points}" fill="none" {style}/>')
            continue
        (x0, y0), (x1, y1) = (cells[src] + 0.5) * cell, (cells[dst] + 0.5) * cell
        arrows.append(f'<line class="move" x1="{x0:.1f}" y1="{y0:.1f}" x2="{x1:.1f}" y2="{y1:.1f}" {style}/>')
    return svg.replace("</svg>", "".join(arrows) + "</svg>")


# -- the statistics as the API serves them (GET /api/stats; the dashboard draws the same numbers) ---------------


def _grid(values: np.ndarray) -> list[list[float | None]]:
    return [[float(v) if math.isfinite(v) else None for v in row] for row in np.asarray(values, dtype=np.float64)]


def candidate_threshold(calibrations: Sequence[Mapping[str, Any]], config_digest: str) -> float | None:
    """The newest threshold calibration of this configuration not applied yet: the candidate to look at."""
    for cal in reversed(list(calibrations)):
        if cal.get("kind") == "threshold" and cal.get("config_digest") == config_digest and not cal.get("applied"):
            return float(cal["threshold"])
    return None


def lab_stats(lab: Any, *, assembly_shots: int = 200) -> dict[str, Any]:
    """``stats_report`` for the running configuration of a lab service (``GET /api/stats`` answers this; the
    dashboard draws it): its statistics book, configured threshold, calibrations and recent shots."""
    config = lab.config
    digest = config.digest()
    _, records = lab.shots(limit=assembly_shots, offset=0)
    shots = [r.to_dict() for r in reversed(records) if r.config_digest == digest]
    return stats_report(
        lab.trap_stats.get(digest), shape=(config.array.ny, config.array.nx), config_digest=digest,
        threshold=config.imaging.threshold, candidate=candidate_threshold(lab.calibrations(), digest), shots=shots,
    )


def stats_report(
    stats: TrapStatistics | None, *, shape: tuple[int, int], config_digest: str, threshold: float | None,
    candidate: float | None, shots: Sequence[Mapping[str, Any]], bins: int = 60,
) -> dict[str, Any]:
    """Everything the physicist's view shows, as JSON-ready data: per-trap maps (``None`` where undefined),
    the imaging histogram of the recent first images with its two fitted populations and the error of the
    threshold in use and of a calibration's candidate, and the assembly figures of ``shots`` (oldest first)."""
    ny, nx = shape
    empty_maps = {k: np.full(shape, np.nan) for k in ("loading_probability", "survival", "defect_rate",
                                                      "disagreement_rate")}
    maps = stats.maps() if stats is not None else empty_maps
    trials = stats.samples()["survival_trials"] if stats is not None else np.zeros(shape, dtype=np.int64)
    recent = stats.recent_counts() if stats is not None else np.zeros(0)
    centres, hist = counts_histogram(recent, bins=bins)
    assembly = assembly_series(shots)
    ttd = assembly["time_to_defect_free_ms"]
    done = ttd[np.isfinite(ttd)]
    return {
        "config_digest": config_digest,
        "shape": [ny, nx],
        "shots": stats.shots if stats is not None else 0,
        "truth_shots": stats.truth_shots if stats is not None else 0,
        "maps": {name: _grid(values) for name, values in maps.items()},
        "survival_trials": np.asarray(trials).astype(int).tolist(),
        "imaging": {
            "histogram": {"centres": centres.tolist(), "counts": hist.tolist()},
            **imaging_summary(recent, current_threshold=threshold, candidate_threshold=candidate),
        },
        "assembly": {
            "shots": len(shots),
            "success_rate": float(np.mean([s["outcome"] == "success" for s in shots])) if shots else None,
            "time_to_defect_free_ms_median": float(np.median(done)) if done.size else None,
            "cycles_histogram": cycles_histogram(assembly["cycles"])[1].astype(int).tolist(),
            "lost_per_cycle_mean": float(assembly["lost"].mean()) if assembly["lost"].size else None,
            "slots_per_cycle_mean": float(assembly["slots"].mean()) if assembly["slots"].size else None,
            "atoms_moved_per_cycle_mean": (
                float(assembly["atoms_moved"].mean()) if assembly["atoms_moved"].size else None
            ),
            "pickups_per_cycle_mean": _nanmean(assembly["pickups"]),
            "lost_by_cause_per_cycle_mean": {
                cause: mean for cause, lost in losses_by_cause(shots).items() if (mean := _nanmean(lost)) is not None
            },
        },
    }


# -- the physicist's view as HTML (the dashboard's tabs) --------------------------------------------------------


def _error_text(row: Mapping[str, Any] | None, label: str) -> str:
    if not row or row.get("threshold") is None:
        return f"{label}: none"
    return f"{label}: {row['threshold']:.1f} counts, detection error {row['error']:.1e}"


def imaging_html(imaging: Mapping[str, Any]) -> str:
    """The fit under the histogram: the two populations and the error each threshold implies."""
    fit = imaging.get("fit")
    if fit is None:
        body = "the counts do not split into two populations yet (too few shots, or an empty or full array)"
        return f'<div id="imaging" data-samples="{imaging["samples"]}" data-fit="0" style="font-size:12px">{body}</div>'
    current = imaging.get("current") or {}
    current_txt = (
        _error_text(current, "threshold in use")
        if current.get("threshold") is not None
        else "threshold in use: fitted by the engine when the configuration was applied"
    )
    return (
        f'<div id="imaging" data-samples="{imaging["samples"]}" data-fit="1" style="font-size:12px">'
        f"{imaging['samples']} sums · empty {fit['mean_empty']:.0f} ± {fit['std_empty']:.0f}, one atom "
        f"{fit['mean_atom']:.0f} ± {fit['std_atom']:.0f} counts ({fit['fraction_filled']:.0%} filled, "
        f"{fit['separation']:.1f} σ apart)<br>{html.escape(current_txt)}<br>"
        f"{html.escape(_error_text(imaging.get('candidate'), 'candidate from the latest calibration'))}<br>"
        f"{html.escape(_error_text(imaging.get('best'), 'best for these counts'))}</div>"
    )


def assembly_html(assembly: Mapping[str, Any]) -> str:
    def num(v: float | None, fmt: str) -> str:
        return "—" if v is None else format(v, fmt)

    return (
        f'<div id="assembly" data-shots="{assembly["shots"]}" style="font-size:12px">'
        f"{assembly['shots']} shots: defect-free {num(assembly['success_rate'], '.0%')}, median time to a "
        f"defect-free array {num(assembly['time_to_defect_free_ms_median'], '.1f')} ms · per rearrangement "
        f"cycle: {num(assembly['slots_per_cycle_mean'], '.1f')} slots, "
        f"{num(assembly['atoms_moved_per_cycle_mean'], '.1f')} atoms moved, "
        f"{num(assembly.get('pickups_per_cycle_mean'), '.1f')} pick-ups, "
        f"{num(assembly['lost_per_cycle_mean'], '.2f')} atoms lost (seen missing in the next image)"
        f"{_losses_table(assembly.get('lost_by_cause_per_cycle_mean') or {})}</div>"
    )


def _losses_table(lost_by_cause: Mapping[str, float]) -> str:
    """The lab's atoms lost per rearrangement cycle, by cause, as a small table (nothing on hardware)."""
    if not lost_by_cause:
        return ""
    rows = "".join(
        f'<tr data-cause="{html.escape(cause)}"><td>{html.escape(cause)}</td><td align="right">{mean:.3f}</td></tr>'
        for cause, mean in sorted(lost_by_cause.items(), key=lambda item: -item[1])
    )
    return (
        '<table id="lost-by-cause" style="font-size:12px"><tr><th align="left">lost by cause (lab)</th>'
        f"<th>atoms per cycle</th></tr>{rows}</table>"
    )


def clamp_cycle(shot: Mapping[str, Any], cycle: int) -> int:
    """The cycle of a recorded shot that the History tab shows when asked for ``cycle`` (the nearest one)."""
    return min(max(cycle, 0), len(shot["cycles"]) - 1)


def history_html(shot: Mapping[str, Any], cycle: int, positions_xy: np.ndarray, *, download_url: str) -> str:
    """A recorded shot (``GET /api/runs/{name}/shots/{index}``) at one cycle: its atom map with the plan drawn
    as the routes the atoms took (through the channels under interstitial routing; straight arrows where a
    run file has no routes), the plan's size (pick-ups where recorded), the atoms the lab lost after it by
    cause (where the lab reported them), whether its camera frame is kept, the stage times, and a link to
    download the run file."""
    cycles = shot["cycles"]
    c = cycles[clamp_cycle(shot, cycle)]
    moves = np.array(c.get("moves") or [], dtype=np.int64).reshape(-1, 2)
    paths = {int(p["source"]): np.asarray(p["points"], dtype=np.float64) for p in c.get("paths") or []}
    svg = plan_svg(c["occupancy"], shot["target"], positions_xy, moves, paths=paths, max_width_px=680)
    stages = " · ".join(f"{k} {v / 1e3:.3f} ms" for k, v in c["stage_us"].items())
    pickups = "" if c.get("pickups") is None else f", {c['pickups']} pick-ups"
    lost = (c.get("truth") or {}).get("lost_by_cause")
    lost_txt = "" if lost is None else "<br>lost after this image (lab): " + (
        ", ".join(f'<span data-cause="{html.escape(k)}">{html.escape(k)} {v}</span>' for k, v in lost.items() if v)
        or "none"
    )
    return (
        f'<div id="history" data-shot-id="{int(shot["shot_id"])}" data-cycle="{c["index"]}" '
        f'data-cycles="{len(cycles)}" data-moves="{len(moves)}" data-paths="{len(paths)}" '
        f'data-frame="{int(bool(c.get("frame")))}" '
        f'data-lost="{"" if lost is None else sum(lost.values())}" style="font-size:12px">'
        f'<b>shot {int(shot["shot_id"])}</b> ({html.escape(shot["outcome"])}), cycle {c["index"]} of '
        f"{len(cycles)}: {c['atoms']} atoms, {c['defects']} missing, plan {c['n_slots']} slots, "
        f"{len(moves)} atoms moved{pickups} · camera frame {'kept' if c.get('frame') else 'not kept'} · "
        f"<a href=\"{html.escape(download_url)}\" download>download the run file</a>{lost_txt}"
        f'<br><span style="color:#555">{html.escape(stages)}</span><br>{svg}</div>'
    )
