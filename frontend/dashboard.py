"""The viser dashboard: live atom map, camera image, stage timings against the paper, history, and controls.

The dashboard is one more client of the lab service, using exactly what the REST API uses (``status()``,
``config``, ``shots()``, ``last_frame()``, ``run()``, ``stop()``, ``shot()``, ``patch_config()``); it never
touches the engine. viser runs its own websocket server on its own thread and port. The service calls our
listener on the engine thread after every shot: the listener only sets an event, and a worker thread of the
dashboard does the drawing, so a slow browser or a slow conversion never delays a shot.

What is drawn is computed by the plain functions of ``frontend.views``.

Authority: the dashboard may do what the REST API allows and no more. With a token (``LLRS_TOKEN``) every
browser tab starts read-only: it sees everything, and its buttons and fields change nothing until it logs in
with the token (a field only that tab sees). A value moved by a tab that has not logged in is put back to the
running configuration. Without a token the server is loopback-only and so is the dashboard, as the API.
"""

from __future__ import annotations

import contextlib
import hmac
import html
import io
import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from engine.config import SystemConfig
from engine.psf import trap_positions_px
from engine.records import ShotRecord
from engine.solvers import ALGORITHMS
from engine.trap_stats import StatsBook
from frontend import views

__all__ = ["Dashboard", "LabClient", "RunFiles", "target_presets"]

log = logging.getLogger("llrs.dashboard")

#: The History tab's camera image when the recorded cycle has no frame kept.
HISTORY_NO_FRAME = "camera: no frame kept for this cycle (llrs serve --keep-frames N keeps them)"
CALIBRATION_IMAGES = 40  # frames a threshold fit takes from the dashboard (as the API's default)

#: The per-trap maps the "Traps" tab offers (statistic -> what it says).
TRAP_MAPS = {
    "survival": "survival per rearrangement cycle",
    "loading_probability": "loading probability",
    "defect_rate": "shots ending with this target trap empty",
    "disagreement_rate": "detected vs simulated ground truth, disagreements",
}


class LabClient(Protocol):
    """The part of ``server.service.LabService`` the dashboard drives (the same calls the REST API makes)."""

    @property
    def config(self) -> SystemConfig: ...

    def status(self) -> Any: ...

    def shots(self, *, limit: int, offset: int) -> tuple[int, list[ShotRecord]]: ...

    def last_frame(self) -> tuple[int, np.ndarray] | None: ...

    def run(self) -> None: ...

    def stop(self) -> None: ...

    def shot(self, *, override: dict[str, Any] | None = None) -> ShotRecord: ...

    def patch_config(self, patch: dict[str, Any]) -> SystemConfig: ...

    def calibrate_threshold(self, *, images: int = 40) -> dict[str, Any]: ...

    def apply_calibration(self, calibration_id: str) -> dict[str, Any]: ...

    def add_listener(self, callback: Callable[[ShotRecord], None]) -> None: ...

    def remove_listener(self, callback: Callable[[ShotRecord], None]) -> None: ...

    def calibrations(self) -> list[dict[str, Any]]: ...

    @property
    def trap_stats(self) -> StatsBook: ...

    @property
    def run_store(self) -> RunFiles | None: ...


class RunFiles(Protocol):
    """The run files the dashboard's history reads (``server.runstore.RunStore``, as ``/api/runs`` does)."""

    def runs(self, *, limit: int = 100) -> list[dict[str, Any]]: ...

    def read_shot(self, name: str, index: int) -> dict[str, Any]: ...

    def read_frame(self, name: str, index: int, cycle: int) -> np.ndarray: ...


def target_presets(config: SystemConfig) -> OrderedDict[str, dict[str, Any]]:
    """Target patterns offered in the dashboard for this array (label -> ``target`` config section).

    The first entry is the configured target. A chain gets centre blocks of several sizes, a left-aligned
    block and every other trap; a grid gets full-width centre bands (what its planners fill)."""
    nx, ny = config.array.nx, config.array.ny
    presets: OrderedDict[str, dict[str, Any]] = OrderedDict()
    presets["as configured"] = config.target.model_dump(mode="json")
    if ny == 1:
        for count in sorted({max(1, nx // 4), max(1, nx // 2), max(1, (nx * 9) // 16)}):
            presets[f"centre block of {count}"] = {"kind": "centre", "count": count}
        half = max(1, nx // 2)
        presets[f"left block of {half}"] = {"kind": "rectangle", "row0": 0, "col0": 0, "rows": 1, "cols": half}
        presets["every other trap"] = {"kind": "mask", "mask": ["".join("1" if i % 2 == 0 else "0" for i in range(nx))]}
    else:
        for rows in sorted({max(1, ny // 4), max(1, ny // 2)}):
            presets[f"centre band of {rows} rows ({rows * nx} atoms)"] = {"kind": "centre", "count": rows * nx}
    return presets


class Dashboard:
    """A viser server showing one lab service. ``start()`` returns the port it listens on."""

    def __init__(
        self,
        service: LabClient,
        *,
        host: str = "127.0.0.1",
        port: int = 8080,
        api_url: str | None = None,
        token: str | None = None,
        history: int = 200,
        timing_shots: int = 50,
        refresh_s: float = 0.5,
        stats_refresh_s: float = 2.0,
    ) -> None:
        self.service = service
        self.host = host
        self.port = port
        self.api_url = api_url
        self._token = token
        self._logged_in: set[int] = set()  # viser client ids that gave the token
        self.history = history
        self.timing_shots = timing_shots
        self.refresh_s = refresh_s
        self.stats_refresh_s = stats_refresh_s  # the physicist's tabs: histograms and maps over many shots
        self._stats_drawn_s = 0.0
        self._stats_key: tuple[Any, ...] | None = None
        self._history_shown: tuple[str, int, int] | None = None
        self._server: Any = None
        self._new_shot = threading.Event()
        self._closing = threading.Event()
        self._worker: threading.Thread | None = None
        self._dicts: OrderedDict[int, dict[str, Any]] = OrderedDict()  # shot_id -> to_dict(), newest last
        self._shown_shot: int | None = None
        self._shown_frame: int | None = None
        self._config_digest: str | None = None
        self._presets: OrderedDict[str, dict[str, Any]] = OrderedDict()
        self._positions = np.zeros((0, 2))
        self._threshold_fit: str | None = None  # id of the last threshold fit, until it is applied
        self._runs: dict[str, dict[str, Any]] = {}
        self._choices: tuple[str, str, int, int] = ("survival", "(none)", 0, 0)
        self.updates = 0  # drawn shots, for tests

    # -- life cycle -------------------------------------------------------------------------------------------

    def start(self) -> int:
        import viser  # imported here: the engine and the API work without a dashboard

        with contextlib.redirect_stdout(io.StringIO()):  # viser's own banner; llrs serve prints the URLs
            self._server = viser.ViserServer(host=self.host, port=self.port, label="LLRS lab", verbose=False)
        self.port = self._server.get_port()
        self._build()
        if self._token is not None:
            self._server.on_client_connect(self._login_panel)
            self._server.on_client_disconnect(lambda client: self._logged_in.discard(client.client_id))
        self.service.add_listener(self._on_shot)
        self._worker = threading.Thread(target=self._loop, name="llrs-dashboard", daemon=True)
        self._worker.start()
        return self.port

    def stop(self) -> None:
        self._closing.set()
        self._new_shot.set()
        self.service.remove_listener(self._on_shot)
        if self._worker is not None:
            self._worker.join(timeout=5)
        if self._server is not None:
            self._server.stop()

    # -- layout -----------------------------------------------------------------------------------------------

    def _build(self) -> None:
        server = self._server
        gui = server.gui
        gui.configure_theme(dark_mode=False, show_logo=False, show_share_button=False, brand_color=(44, 120, 200))
        gui.set_panel_label("LLRS lab")
        gui.main_panel.dock_left()
        gui.main_panel.set_width(360)

        # Left: status, controls, simulation knobs.
        api = f" · [API docs]({self.api_url}/docs)" if self.api_url else ""
        gui.add_markdown(f"### LLRS lab server{api}")
        self.h_status = gui.add_html(self._status_html())
        with gui.add_folder("Shots"):
            self.b_run = gui.add_button("Run continuously", color="green")
            self.b_stop = gui.add_button("Stop", color="red")
            self.b_once = gui.add_button("One shot")
        with gui.add_folder("Problem"):
            cfg = self.service.config
            algorithms = list(ALGORITHMS) if cfg.solver.algorithm in ALGORITHMS else [cfg.solver.algorithm, *ALGORITHMS]
            self.d_algorithm = gui.add_dropdown("Algorithm", options=algorithms, initial_value=cfg.solver.algorithm)
            self._presets = target_presets(cfg)
            self.d_target = gui.add_dropdown("Target", options=list(self._presets), initial_value="as configured")
            self.n_max_cycles = gui.add_number("Max cycles", initial_value=cfg.loop.max_cycles, min=1, max=100, step=1)
            self.b_problem = gui.add_button("Apply problem")
        with gui.add_folder("Calibration"):
            self.b_fit_threshold = gui.add_button(f"Fit threshold ({CALIBRATION_IMAGES} frames)")
            self.h_calibration = gui.add_html("")
            self.b_apply_threshold = gui.add_button("Apply fitted threshold", disabled=True)
        self.f_sim = gui.add_folder("Simulated lab")
        with self.f_sim:
            self.s_loading = gui.add_slider(
                "Loading prob.", min=0.05, max=1.0, step=0.01, initial_value=cfg.sim.loading_probability
            )
            self.s_transfer = gui.add_slider(
                "Survival / transfer", min=0.8, max=1.0, step=0.001, initial_value=cfg.sim.survival_transfer
            )
            self.s_step = gui.add_slider(
                "Survival / step", min=0.8, max=1.0, step=0.001, initial_value=cfg.sim.survival_step
            )
            self.c_lossless = gui.add_checkbox("Lossless", initial_value=cfg.sim.lossless)
            self.b_sim = gui.add_button("Apply simulation")
        self.f_sim.visible = self._simulated(cfg)
        self.h_message = gui.add_html("")

        # Left, below the controls: timing and history. Right: the atom map per cycle and the camera frame.
        # Middle (viser's 3D canvas): the latest final state over the camera frame, to pan and zoom.
        stats = gui.add_panel()
        with stats.add_tab("Stage timing"):
            self.h_timing = gui.add_html(views.timing_html([], "1x64", shots=0))
        stats.dock_below(gui.main_panel)
        live = gui.add_panel()
        with live.add_tab("Atoms"):
            self.h_atoms = gui.add_html(
                '<div id="atom-map" data-shot-id="" style="color:#777">waiting for the first shot…</div>'
            )
            self.i_camera = gui.add_image(
                np.zeros((8, 32, 3), dtype=np.uint8), label="camera: no frame yet", format="png"
            )
            empty = (np.zeros(1), np.zeros(1))
            self.p_success = gui.add_uplot(
                data=empty,
                series=(
                    {"label": "shot"},
                    {"label": "defect-free % (last 20 shots)", "stroke": views.COLOURS["in_place"], "width": 2},
                ),
                title="Success rate over time",
                scales={"x": {"time": False}, "y": {"auto": False, "range": [0, 100]}},
                height=150,
            )
            self.p_cycles = gui.add_uplot(
                data=empty,
                series=(
                    {"label": "shot"},
                    {"label": "rearrangement cycles", "stroke": views.COLOURS["ours"], "width": 0,
                     "points": {"show": True, "size": 5, "fill": views.COLOURS["ours"]}},
                ),
                title="Cycles per shot",
                scales={"x": {"time": False}},
                height=130,
            )
        self._build_physics_tabs(live)
        live.dock_right()
        live.set_width(720)
        server.scene.set_up_direction("+z")
        self._scene_key: tuple[int, ...] | None = None
        self.sc_atoms: Any = None

        self.b_run.on_click(self._guarded(lambda: self._command("run", self.service.run)))
        self.b_stop.on_click(self._guarded(lambda: self._command("stop", self.service.stop)))
        self.b_once.on_click(self._guarded(lambda: self._command("one shot", self.service.shot)))
        self.b_problem.on_click(self._guarded(lambda: self._apply(self._problem_patch(), "problem")))
        self.b_sim.on_click(self._guarded(lambda: self._apply(self._sim_patch(), "simulation")))
        self.b_fit_threshold.on_click(self._guarded(self._fit_threshold))
        self.b_apply_threshold.on_click(self._guarded(self._apply_threshold))
        self.b_reset_stats.on_click(self._guarded(self._reset_stats))
        self.b_runs.on_click(self._guarded(self._list_runs))
        for field in (self.d_algorithm, self.d_target, self.n_max_cycles, self.s_loading, self.s_transfer,
                      self.s_step, self.c_lossless):
            field.on_update(self._put_back_unless_allowed)
        for field in (self.d_map, self.d_run, self.n_shot, self.n_cycle):
            field.on_update(self._history_or_back)
        self._sync_config(force=True)

    def _build_physics_tabs(self, live: Any) -> None:
        """The physicist's view: imaging histogram, per-trap maps, assembly figures, recorded shots."""
        gui = self._server.gui
        empty = (np.zeros(1), np.zeros(1))
        with live.add_tab("Imaging"):
            self.h_imaging = gui.add_html('<div id="imaging" data-samples="0" style="color:#777">no images yet</div>')
            self.p_histogram = gui.add_uplot(
                data=(np.zeros(1),) * 6,
                series=(
                    {"label": "counts"},
                    {"label": "traps", "stroke": "#555", "fill": "rgba(120,120,120,0.25)", "width": 1},
                    {"label": "fit: empty", "stroke": views.COLOURS["missing"], "width": 2},
                    {"label": "fit: one atom", "stroke": views.COLOURS["in_place"], "width": 2},
                    {"label": "threshold in use", "stroke": "#000", "width": 2},
                    {"label": "candidate (calibration)", "stroke": "#ff7f0e", "width": 2, "dash": [6, 4]},
                ),
                title="PSF-weighted counts per trap (first image of recent shots)",
                scales={"x": {"time": False}},
                height=220,
            )
            self.p_histogram_shot = gui.add_uplot(
                data=empty,
                series=({"label": "counts"}, {"label": "traps, latest shot", "stroke": views.COLOURS["ours"],
                                              "fill": "rgba(76,120,200,0.2)", "width": 1}),
                title="This shot (every image)",
                scales={"x": {"time": False}},
                height=140,
            )
        with live.add_tab("Traps"):
            self.d_map = gui.add_dropdown("Statistic", options=list(TRAP_MAPS), initial_value="survival")
            self.h_traps = gui.add_html('<div id="trap-maps" data-shots="0" style="color:#777">no shots yet</div>')
            self.b_reset_stats = gui.add_button("Reset statistics (this configuration)")
        with live.add_tab("Assembly"):
            self.h_assembly = gui.add_html('<div id="assembly" data-shots="0" style="color:#777">no shots yet</div>')
            self.p_ttd = gui.add_uplot(
                data=empty,
                series=(
                    {"label": "shot"},
                    {"label": "time to a defect-free array (ms)", "stroke": views.COLOURS["ours"], "width": 0,
                     "points": {"show": True, "size": 5}},
                ),
                title="Time to a defect-free array",
                scales={"x": {"time": False}},
                height=140,
            )
            self.p_cycles_hist = gui.add_uplot(
                data=empty,
                series=({"label": "rearrangement cycles"}, {"label": "shots", "stroke": "#555",
                                                            "fill": "rgba(120,120,120,0.25)", "width": 1}),
                title="Cycles per shot (histogram)",
                scales={"x": {"time": False}},
                height=120,
            )
            self.p_plan = gui.add_uplot(
                data=(np.zeros(1),) * 5,
                series=(
                    {"label": "cycle"},
                    {"label": "slots", "stroke": views.COLOURS["ours"], "width": 1},
                    {"label": "atoms moved", "stroke": views.COLOURS["in_place"], "width": 1},
                    {"label": "pick-ups", "stroke": views.COLOURS["spare"], "width": 1, "dash": [4, 3]},
                    {"label": "atoms lost", "stroke": views.COLOURS["missing"], "width": 1},
                ),
                title="Plan size, pick-ups and atoms lost, per rearrangement cycle",
                scales={"x": {"time": False}},
                height=140,
            )
        with live.add_tab("History"):
            self.b_runs = gui.add_button("List run files")
            self.d_run = gui.add_dropdown("Run file", options=["(none)"], initial_value="(none)")
            self.n_shot = gui.add_number("Shot in file", initial_value=0, min=0, step=1)
            self.n_cycle = gui.add_number("Cycle", initial_value=0, min=0, step=1)
            self.h_history = gui.add_html('<div id="history" style="color:#777">pick a run file</div>')
            self.i_history_frame = gui.add_image(
                np.zeros((8, 32, 3), dtype=np.uint8), label=HISTORY_NO_FRAME, format="png"
            )

    # -- authority --------------------------------------------------------------------------------------------

    def _allowed(self, event: Any) -> bool:
        """True if the client behind a GUI event may change things (no token set, or it logged in)."""
        if self._token is None or event.client_id in self._logged_in:
            return True
        self._say("read-only: log in with the server's token (LLRS_TOKEN) to run shots or change the configuration",
                  error=True)
        return False

    def _guarded(self, action: Callable[[], None]) -> Callable[[Any], None]:
        """A click handler that runs ``action`` only for a client allowed to change things."""

        def on_click(event: Any) -> None:
            if self._allowed(event):
                action()

        return on_click

    def _put_back_unless_allowed(self, event: Any) -> None:
        """A field moved by a client that may not change things goes back to the running configuration (the
        fields are shared by every tab)."""
        if event.client_id is not None and not self._allowed(event):
            self._sync_config(force=True)

    def login(self, client_id: int, token: str) -> bool:
        """Let viser client ``client_id`` change things if ``token`` is the server's (constant-time check)."""
        if self._token is not None and hmac.compare_digest(token.encode(), self._token.encode()):
            self._logged_in.add(client_id)
            return True
        return False

    def _login_panel(self, client: Any) -> None:
        """A login field and button that only this client sees."""
        with client.gui.add_folder("Log in to control"):
            field = client.gui.add_text("Token", initial_value="", hint="LLRS_TOKEN of the server")
            button = client.gui.add_button("Log in")
            note = client.gui.add_markdown("read-only until you log in")

        def log_in(event: Any) -> None:
            ok = self.login(client.client_id, field.value)
            field.value = ""
            note.content = "logged in: the controls act" if ok else "wrong token; still read-only"

        button.on_click(log_in)

    # -- controls ---------------------------------------------------------------------------------------------

    @staticmethod
    def _simulated(cfg: SystemConfig) -> bool:
        devices = cfg.devices
        return getattr(devices, "camera", "sim") == "sim" and getattr(devices, "awg", "sim") == "sim"

    def _problem_patch(self) -> dict[str, Any]:
        patch: dict[str, Any] = {
            "solver": {"algorithm": self.d_algorithm.value},
            "loop": {"max_cycles": int(self.n_max_cycles.value)},
        }
        if self.d_target.value != "as configured":
            target = {"kind": "centre", "count": None, "row0": 0, "col0": 0, "rows": None, "cols": None, "mask": None}
            target.update(self._presets[self.d_target.value])
            patch["target"] = target
        return patch

    def _sim_patch(self) -> dict[str, Any]:
        return {
            "sim": {
                "loading_probability": round(float(self.s_loading.value), 4),
                "survival_transfer": round(float(self.s_transfer.value), 4),
                "survival_step": round(float(self.s_step.value), 4),
                "lossless": bool(self.c_lossless.value),
            }
        }

    def _say(self, text: str, *, error: bool = False) -> None:
        colour = "#d62728" if error else "#2c6e2c"
        self.h_message.content = f'<div style="font-size:12px;color:{colour};white-space:pre-wrap">{text}</div>'

    def _command(self, name: str, call: Callable[[], Any]) -> None:
        try:
            call()
            self._say(f"{name}: ok")
        except Exception as err:  # shown to the person; the dashboard keeps running
            self._say(f"{name} failed: {err}", error=True)
        self._new_shot.set()

    def _apply(self, patch: dict[str, Any], what: str) -> None:
        try:
            self.service.patch_config(patch)
        except ValueError as err:  # ConfigRejected: the field and the reason
            self._say(f"{what} not applied:\n{err}", error=True)
            return
        self._say(f"{what} applied (between shots)")
        self._new_shot.set()

    def _fit_threshold(self) -> None:
        """Fit the occupancy threshold to fresh frames and show it beside the configured one (nothing applied)."""
        try:
            fit = self.service.calibrate_threshold(images=CALIBRATION_IMAGES)
        except Exception as err:  # shown to the person; the dashboard keeps running
            self._say(f"threshold fit failed: {err}", error=True)
            return
        self._threshold_fit = fit["id"]
        if fit["current_threshold"] is None:
            current = "configured: none (the engine fitted one when the configuration was applied)"
        else:
            current = f"configured: {fit['current_threshold']:.1f} counts, error {1 - fit['current_fidelity']:.1e}"
        self.h_calibration.content = (
            f'<div style="font-size:12px">fitted: {fit["threshold"]:.1f} counts, predicted error '
            f"{1 - fit['fidelity']:.1e} ({fit['images']} frames, {fit['fraction_filled']:.0%} filled)<br>"
            f"{current}</div>"
        )
        self.b_apply_threshold.disabled = False
        self._say("threshold fitted; apply it to use it")

    def _reset_stats(self) -> None:
        self.service.trap_stats.reset(self.service.config.digest())
        self._stats_key = None
        self._say("statistics of this configuration reset")

    def _list_runs(self) -> None:
        store = self.service.run_store
        runs = store.runs() if store is not None else []
        self._runs = {r["name"]: r for r in runs}
        self.d_run.options = list(self._runs) or ["(none)"]
        self._say(f"{len(runs)} run files" if runs else "no run files yet")

    def _history_or_back(self, event: Any) -> None:
        """History and map choices are shared by every tab: a client that may not change things gets the
        previous choice back; otherwise the view follows. (The dashboard's own changes, without a client, are
        not choices: putting a choice back, or new options, must not overwrite the last allowed one.)"""
        if event.client_id is not None and not self._allowed(event):
            self._restore_choices()
            return
        if event.client_id is not None:
            self._choices = (self.d_map.value, self.d_run.value, int(self.n_shot.value), int(self.n_cycle.value))
        self._stats_key = None
        self._new_shot.set()

    def _restore_choices(self) -> None:
        chosen_map, run, shot, cycle = self._choices
        self.d_map.value, self.n_shot.value, self.n_cycle.value = chosen_map, shot, cycle
        if run in self.d_run.options:
            self.d_run.value = run

    def _apply_threshold(self) -> None:
        if self._threshold_fit is not None:
            fit, self._threshold_fit = self._threshold_fit, None
            self.b_apply_threshold.disabled = True
            self._command("apply fitted threshold", lambda: self.service.apply_calibration(fit))

    def _sync_config(self, *, force: bool = False) -> None:
        """Show the running configuration in the controls (it may have changed through the API)."""
        cfg = self.service.config
        digest = cfg.digest()
        if digest == self._config_digest and not force:
            return
        self._config_digest = digest
        self._positions = trap_positions_px(cfg)
        self._column = views.paper_column(cfg.array.nx, cfg.array.ny)
        if cfg.solver.algorithm in self.d_algorithm.options:
            self.d_algorithm.value = cfg.solver.algorithm
        self._presets = target_presets(cfg)
        self.d_target.options = list(self._presets)
        self.d_target.value = "as configured"
        self.n_max_cycles.value = cfg.loop.max_cycles
        self.s_loading.value = cfg.sim.loading_probability
        self.s_transfer.value = max(0.8, cfg.sim.survival_transfer)
        self.s_step.value = max(0.8, cfg.sim.survival_step)
        self.c_lossless.value = cfg.sim.lossless
        self.f_sim.visible = self._simulated(cfg)

    # -- drawing ----------------------------------------------------------------------------------------------

    def _on_shot(self, record: ShotRecord) -> None:
        """On the engine thread: only wake the worker."""
        self._new_shot.set()

    def _status_html(self) -> str:
        status = self.service.status().model_dump(mode="json")
        colour = views.state_colour(status["state"])
        text = views.status_markdown(status).replace("  \n", "<br>")
        text = text.replace("**", "").replace("`", "")
        return (
            f'<div id="lab-status" data-state="{status["state"]}" data-shots="{status["shots_done"]}" '
            f'style="font-size:12px;border-left:4px solid {colour};padding-left:6px">{text}</div>'
        )

    def _refresh(self) -> None:
        self._sync_config()
        self.h_status.content = self._status_html()
        total, records = self.service.shots(limit=self.history, offset=0)
        if not records:
            return
        newest = records[0]
        for record in reversed(records):  # oldest first, so the dict keeps shot order
            if record.shot_id not in self._dicts:
                rearrangements = sum(1 for c in record.cycles if c.n_slots > 0)
                self._dicts[record.shot_id] = record.to_dict() | {"rearrangements": rearrangements}
        keep = {r.shot_id for r in records}
        for shot_id in [k for k in self._dicts if k not in keep]:
            del self._dicts[shot_id]
        if newest.shot_id == self._shown_shot:
            return
        shots = list(self._dicts.values())
        latest = self._dicts[newest.shot_id]
        frame = self.service.last_frame()
        if frame is not None and frame[0] != self._shown_frame:
            rgb, note = views.frame_to_rgb(frame[1], min_width=600)
            self.i_camera.image = rgb
            self.i_camera.label = f"camera, final image of shot {frame[0]}: {note}"
            self._shown_frame = frame[0]
        if len(self._positions) == len(latest["target"]) * len(latest["target"][0]):
            self.h_atoms.content = views.shot_html(latest, self._positions, width_px=720)
        self._draw_scene(latest, frame if frame is not None and frame[0] == newest.shot_id else None)
        recent = shots[-self.timing_shots :]
        rows = views.stage_rows(recent, self._column)
        self.h_timing.content = views.timing_html(rows, self._column, shots=len(recent))
        ids, rate, cycles = views.history_series(shots)
        self.p_success.data = (ids, rate)
        self.p_cycles.data = (ids, cycles)
        self._shown_shot = newest.shot_id
        self.updates += 1

    def _draw_scene(self, shot: dict[str, Any], frame: tuple[int, np.ndarray] | None) -> None:
        """The final state as discs over the camera frame, in trap-pitch units, seen from above.

        The canvas between the side panels is tall and narrow, so a picture much wider than tall (a chain) is
        turned a quarter turn to run top to bottom."""
        scene = self._server.scene
        points, colours, pitch = views.atom_points(shot["cycles"][-1]["occupancy"], shot["target"], self._positions)
        key = (len(points), *np.round(points[[0, -1], :2].ravel(), 3).tolist())
        marked = np.any(colours != np.array(views._rgb(views.COLOURS["empty"]), dtype=np.uint8), axis=1)
        all_points = points
        points, colours = points[marked], colours[marked]  # empty traps: the camera frame shows them
        if key != self._scene_key:
            lo, hi = all_points[:, :2].min(axis=0), all_points[:, :2].max(axis=0)
            span = hi - lo
            turn = bool(span[0] > 2 * span[1])
            half = np.sqrt(0.5)
            # a frame node holds the picture; a quarter turn about z (x -> -y) when turning
            self._view = scene.add_frame(
                "/view", show_axes=False, wxyz=(half, 0.0, 0.0, -half) if turn else (1.0, 0.0, 0.0, 0.0)
            )
            self.sc_atoms = scene.add_point_cloud(
                "/view/atoms", points, colours, point_size=0.4, point_shape="circle", point_shading="flat",
                position=(0.0, 0.0, 0.05),
            )
            centre = (lo + hi) / 2
            cx, cy = (centre[1], -centre[0]) if turn else (centre[0], centre[1])
            extent = float(max(span)) + 4.0
            cam = self._server.initial_camera
            cam.look_at = (float(cx), float(cy), 0.0)
            # far enough for a narrow canvas to show the whole array
            cam.position = (float(cx), float(cy) - 0.02 * extent, 0.75 * extent)
            self._scene_key = key
        else:
            self.sc_atoms.points = points
            self.sc_atoms.colors = colours
        if frame is not None:
            cfg = self.service.config
            bx, by = cfg.camera.binning
            rgb, _ = views.frame_to_rgb(frame[1], fold=False, max_side=2048)
            h, w = frame[1].shape
            scene.add_image(  # turned over about x, so that frame row 0 is at the top (largest y)
                "/view/camera", rgb, render_width=w * bx / pitch, render_height=h * by / pitch,
                position=((w * bx / 2 - 0.5) / pitch, -(h * by / 2 - 0.5) / pitch, 0.0), wxyz=(0.0, 1.0, 0.0, 0.0),
            )

    def _loop(self) -> None:
        while not self._closing.is_set():
            self._new_shot.wait(self.refresh_s)
            self._new_shot.clear()
            if self._closing.is_set():
                return
            try:
                self._refresh()
                self._refresh_physics()
            except Exception:  # never let one bad frame kill the dashboard
                log.exception("dashboard refresh failed")

    # -- the physicist's view ---------------------------------------------------------------------------------

    def _refresh_physics(self) -> None:
        """Histograms, maps and assembly figures (at most every ``stats_refresh_s``: they summarize many shots,
        and a 64x128 map is a large picture), and the recorded shot the History tab points at."""
        self._draw_history()
        now = time.monotonic()
        digest = self.service.config.digest()
        stats = self.service.trap_stats.get(digest)
        key = (digest, stats.shots if stats is not None else 0, self.d_map.value)
        if key == self._stats_key or now - self._stats_drawn_s < self.stats_refresh_s and self._stats_key:
            return
        report = views.lab_stats(self.service, assembly_shots=self.history)
        self._draw_imaging(report, stats)
        self._draw_traps(report)
        self._draw_assembly(report)
        self._stats_key, self._stats_drawn_s = key, now

    def _draw_imaging(self, report: dict[str, Any], stats: Any) -> None:
        imaging = report["imaging"]
        centres = np.asarray(imaging["histogram"]["centres"])
        hist = np.asarray(imaging["histogram"]["counts"])
        if centres.size < 2 or stats is None:
            return
        empty, atom = views.population_curves(centres, imaging["fit"], int(hist.sum()))
        top = float(hist.max()) if hist.size else 1.0
        current = (imaging["current"] or {}).get("threshold")
        candidate = (imaging["candidate"] or {}).get("threshold")
        self.p_histogram.data = (
            centres, hist, empty, atom, views.threshold_series(centres, top, current),
            views.threshold_series(centres, top, candidate),
        )
        shot_centres, shot_hist = views.counts_histogram(stats.latest_counts, bins=40)
        if shot_centres.size:
            self.p_histogram_shot.data = (shot_centres, shot_hist)
        self.h_imaging.content = views.imaging_html(imaging)

    def _draw_traps(self, report: dict[str, Any]) -> None:
        if report["shots"] == 0 or len(self._positions) != report["shape"][0] * report["shape"][1]:
            return
        name = self.d_map.value
        values = np.array(report["maps"][name], dtype=np.float64)
        samples = np.array(report["survival_trials"]) if name == "survival" else None
        svg = views.heatmap_svg(values, self._positions, name=name, samples=samples, max_width_px=680)
        worst = ", ".join(f"trap {t}: {v:.3f}" for t, v in views.worst_traps(values))
        self.h_traps.content = (
            f'<div id="trap-maps" data-shots="{report["shots"]}" data-name="{name}" style="font-size:12px">'
            f"<b>{TRAP_MAPS[name]}</b> over {report['shots']} shots (hover a trap for its numbers; red 0, "
            f"yellow 0.5, green 1, grey: no samples)<br>lowest: {worst or '—'}<br>{svg}</div>"
        )

    def _draw_assembly(self, report: dict[str, Any]) -> None:
        shots = list(self._dicts.values())
        if not shots:
            return
        a = views.assembly_series(shots)
        done = np.isfinite(a["time_to_defect_free_ms"])  # defect-free shots only: a NaN blanks a uPlot plot
        if done.any():
            self.p_ttd.data = (a["shot_id"][done], a["time_to_defect_free_ms"][done])
        if a["shot_id"].size:
            values, hist = views.cycles_histogram(a["cycles"])
            self.p_cycles_hist.data = (values, hist)
        known = np.isfinite(a["pickups"])  # a cycle whose pick-ups are not known is left out: a NaN blanks the plot
        if known.any():
            cycle = np.arange(a["slots"].size, dtype=np.float64)
            self.p_plan.data = tuple(v[known] for v in (cycle, a["slots"], a["atoms_moved"], a["pickups"], a["lost"]))
        self.h_assembly.content = views.assembly_html(report["assembly"])

    def _draw_history(self) -> None:
        run = self.d_run.value
        store = self.service.run_store
        if store is None or run not in self._runs:
            return
        shown = (run, int(self.n_shot.value), int(self.n_cycle.value))
        if shown == self._history_shown:
            return
        try:
            shot = store.read_shot(run, shown[1])
        except (OSError, IndexError, KeyError, ValueError) as err:
            self.h_history.content = f'<div id="history" style="color:#d62728">{html.escape(str(err))}</div>'
            self._history_shown = shown
            return
        cycle = views.clamp_cycle(shot, shown[2])
        if shot["cycles"][cycle].get("frame"):  # the frame first: once the text names the cycle, all of it is shown
            rgb, note = views.frame_to_rgb(store.read_frame(run, shown[1], cycle), min_width=600)
            self.i_history_frame.image = rgb
            self.i_history_frame.label = f"camera, shot {int(shot['shot_id'])} cycle {cycle}: {note}"
        else:
            self.i_history_frame.image = np.zeros((8, 32, 3), dtype=np.uint8)
            self.i_history_frame.label = HISTORY_NO_FRAME
        download = f"{self.api_url}/api/runs/{run}" if self.api_url else f"/api/runs/{run}"
        self.h_history.content = views.history_html(shot, shown[2], self._positions, download_url=download)
        self._history_shown = shown
