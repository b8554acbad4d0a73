"""The dashboard without a browser: it serves viser's page, draws every shot from the service, and its
controls go through the service (a refused change is shown, and changes nothing)."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace

import httpx
import numpy as np
import pytest

from conftest import wait_until
from dashboard_fakes import dashboard_on_fake_lab
from frontend import views
from frontend.dashboard import Dashboard
from server.runstore import FrameKeeping, RunStore
from server.service import LabService
from server_fakes import fake_lab_service

pytest.importorskip("viser")


@pytest.fixture
def dash(tmp_path: Path) -> Iterator[tuple[Dashboard, LabService]]:
    with dashboard_on_fake_lab(tmp_path / "runs", keep_images=True, frames=FrameKeeping(every_nth_shot=2)) as running:
        yield running


def test_serves_the_viser_page(dash: tuple[Dashboard, LabService]) -> None:
    dashboard, _ = dash
    assert dashboard.port > 0
    r = httpx.get(f"http://127.0.0.1:{dashboard.port}/")
    assert r.status_code == 200 and "<html" in r.text.lower()


def test_draws_each_shot(dash: tuple[Dashboard, LabService]) -> None:
    dashboard, service = dash
    record = service.shot()
    wait_until(lambda: dashboard.updates >= 1, what="the dashboard's first update")
    assert f'data-shot-id="{record.shot_id}"' in dashboard.h_atoms.content
    assert f'data-outcome="{record.outcome.value}"' in dashboard.h_atoms.content
    assert "I.acquire" in dashboard.h_timing.content
    assert dashboard.i_camera.label.startswith(f"camera, final image of shot {record.shot_id}")
    assert len(dashboard.p_success.data[0]) == 1
    wait_until(lambda: 'data-shots="1"' in dashboard.h_status.content, what="the status to show one shot")


def test_controls_drive_the_service(dash: tuple[Dashboard, LabService]) -> None:
    dashboard, service = dash
    dashboard._command("run", service.run)
    wait_until(lambda: service.status().shots_done >= 3, what="three shots")
    dashboard._command("stop", service.stop)
    assert not service.running
    dashboard.s_loading.value = 0.9
    dashboard.c_lossless.value = True
    dashboard._apply(dashboard._sim_patch(), "simulation")
    assert service.config.sim.loading_probability == 0.9 and service.config.sim.lossless is True
    dashboard.d_target.value = "centre block of 16"
    dashboard._apply(dashboard._problem_patch(), "problem")
    assert service.config.target.count == 16
    # the controls follow the running config
    wait_until(lambda: dashboard.d_target.value == "as configured", what="the target control")


def test_a_refused_change_is_shown_and_changes_nothing(dash: tuple[Dashboard, LabService]) -> None:
    dashboard, service = dash
    before = service.config
    dashboard._apply({"solver": {"algorithm": "refuse"}}, "problem")
    assert "problem not applied" in dashboard.h_message.content and "refuse" in dashboard.h_message.content
    assert service.config == before


def test_physicist_tabs_show_maps_assembly_and_a_recorded_shot(dash: tuple[Dashboard, LabService]) -> None:
    dashboard, service = dash
    records = [service.shot() for _ in range(3)]
    ny, nx = service.config.array.ny, service.config.array.nx
    wait_until(lambda: f'data-shots="{len(records)}"' in dashboard.h_traps.content, what="the trap maps")
    assert f'data-rows="{ny}" data-cols="{nx}"' in dashboard.h_traps.content
    assert dashboard.h_traps.content.count("<rect") == ny * nx
    wait_until(lambda: 'data-shots="3"' in dashboard.h_assembly.content, what="the assembly panel")
    assert len(dashboard.p_cycles_hist.data[0]) >= 1
    assert any(r.cycles[0].n_slots for r in records)  # (the fake lab's seeded loading: shots rearrange)
    assert "pick-ups" in dashboard.h_assembly.content
    assert 'data-cause="released"' in dashboard.h_assembly.content  # the loss-by-cause table
    assert dashboard.p_plan.data[3].size >= 1  # the pick-ups series
    service.run_store.flush()  # type: ignore[union-attr]
    dashboard._list_runs()
    dashboard.d_run.value = dashboard.d_run.options[0]
    dashboard.n_shot.value = 1
    dashboard._history_shown = None
    wait_until(lambda: f'data-shot-id="{records[1].shot_id}"' in dashboard.h_history.content, what="the history")
    assert "download the run file" in dashboard.h_history.content
    # the lab's losses after the cycle's image, read back from the run file; shot 1 kept no frame (every 2nd)
    released = records[1].cycles[0].lab_report["lost_by_cause"]["released"]
    assert f'data-lost="{released}"' in dashboard.h_history.content
    assert 'data-frame="0"' in dashboard.h_history.content
    assert dashboard.i_history_frame.label.startswith("camera: no frame kept")
    # shot 2 kept every cycle's frame: stepping through its cycles shows each one
    for cycle in range(len(records[2].cycles)):
        dashboard.n_shot.value, dashboard.n_cycle.value = 2, cycle
        dashboard._history_shown = None
        wait_until(lambda c=cycle: f'data-cycle="{c}" data-cycles' in dashboard.h_history.content
                   and f"shot {records[2].shot_id} cycle {c}:" in dashboard.i_history_frame.label,
                   what=f"cycle {cycle}'s frame")
        assert 'data-frame="1"' in dashboard.h_history.content
        assert dashboard.i_history_frame.image.shape != (8, 32, 3)  # the frame drawn, not the placeholder


def test_new_controls_are_read_only_without_the_token(tmp_path: Path) -> None:
    """Reset, run-file listing and the shared map/history choices obey the token like every other control."""
    with fake_lab_service(tmp_path / "runs") as service:
        dashboard = Dashboard(service, port=0, refresh_s=0.05, token="dash-token")
        dashboard.start()
        try:
            service.shot()
            digest = service.config.digest()
            stranger = SimpleNamespace(client_id=41)
            dashboard._guarded(dashboard._reset_stats)(stranger)
            assert service.trap_stats.get(digest) is not None  # not reset
            dashboard._guarded(dashboard._list_runs)(stranger)
            assert list(dashboard.d_run.options) == ["(none)"]  # not listed
            dashboard.d_map.value = "loading_probability"
            dashboard._history_or_back(stranger)
            assert dashboard.d_map.value == "survival"  # put back
            assert dashboard.login(7, "dash-token")
            member = SimpleNamespace(client_id=7)
            dashboard.d_map.value = "loading_probability"
            dashboard._history_or_back(member)
            assert dashboard.d_map.value == "loading_probability"
            dashboard._guarded(dashboard._reset_stats)(member)
            assert service.trap_stats.get(digest) is None
        finally:
            dashboard.stop()


def test_a_recorded_interstitial_shot_shows_each_atom_route_through_the_channels(tmp_path: Path) -> None:
    """On the simulated lab under interstitial routing (the repair planner), a shot read back from its run file
    draws each moved atom's route as a polyline whose corners leave the traps for the channels between them,
    not as straight arrows."""
    from engine.config import load_config
    from server.serve import engine_host_factory

    config = load_config(Path(__file__).resolve().parents[1] / "examples/grid-16x32.yaml")
    config = config.model_copy(update={
        "array": config.array.model_copy(update={"routing": "interstitial"}),
        "solver": config.solver.model_copy(update={"algorithm": "repair", "strategy": None}),
        "sim": config.sim.model_copy(update={"lossless": True, "seed": 3}),
    })  # fmt: skip
    factory = engine_host_factory(in_process=False, cpu=None)
    service = LabService(engine_thread=factory(config), engine_factory=factory, config=config,
                         store=RunStore(tmp_path / "runs"), pause_s=0.0).start()
    dashboard = Dashboard(service, port=0, refresh_s=0.05)
    dashboard.start()
    try:
        record = service.shot()
        moved = record.cycles[0].atoms_moved
        assert moved > 0
        service.run_store.flush()  # type: ignore[union-attr]
        dashboard._list_runs()
        dashboard.d_run.value = dashboard.d_run.options[0]
        dashboard.n_shot.value, dashboard.n_cycle.value = 0, 0
        dashboard._history_shown = None
        wait_until(lambda: f'data-shot-id="{record.shot_id}" data-cycle="0"' in dashboard.h_history.content,
                   what="the recorded shot")
        content = dashboard.h_history.content
        _, across, _ = views.trap_layout(dashboard._positions)
    finally:
        dashboard.stop()
        service.close()
    assert f'data-moves="{moved}" data-paths="{moved}"' in content
    routes = re.findall(r'<polyline class="move path" points="([^"]+)"', content)
    assert len(routes) == moved and '<line class="move"' not in content
    cell = min(22.0, 680 / across)  # the History tab's picture: 680 px across at most
    for route in routes:
        xy = np.array([[float(v) for v in p.split(",")] for p in route.split()]) / cell - 0.5  # in picture cells
        assert len(xy) >= 3  # out of the trap into a channel, along, back onto a trap
        assert np.allclose(xy[[0, -1]], np.round(xy[[0, -1]]), atol=0.01)  # starts and ends on traps
        inner = xy[1:-1]
        assert np.all(np.any(np.abs(inner - np.round(inner)) > 0.4, axis=1))  # every turn is in a channel
