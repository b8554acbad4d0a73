"""The dashboard on a fake lab (``server_fakes.FakeEngine`` behind a real ``LabService``), for the dashboard tests."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from engine.engine import EngineThread
from frontend.dashboard import Dashboard
from server.runstore import FrameKeeping, RunStore
from server.service import LabService
from server_fakes import FakeEngine, example_config


@contextmanager
def dashboard_on_fake_lab(
    runs: Path, *, keep_images: bool = False, frames: FrameKeeping | None = None
) -> Iterator[tuple[Dashboard, LabService]]:
    """A started dashboard (any free port, refreshed every 50 ms) over a service running fake shots; stored
    runs go to ``runs`` (keeping camera frames as ``frames`` says). Both are stopped on exit."""
    service = LabService(
        engine_thread=EngineThread(lambda: FakeEngine(example_config(), keep_images=keep_images)),  # type: ignore[arg-type, return-value]
        store=RunStore(runs, frames=frames),
        pause_s=0.01,
    ).start()
    dashboard = Dashboard(service, port=0, refresh_s=0.05)
    dashboard.start()
    try:
        yield dashboard, service
    finally:
        dashboard.stop()
        service.close()
