"""The dashboard makes threshold calibration an everyday step: fit from fresh frames, see the fitted threshold
with its predicted error beside the configured one, apply it as an ordinary configuration change."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from dashboard_fakes import dashboard_on_fake_lab
from frontend.dashboard import Dashboard
from server.service import LabService

pytest.importorskip("viser")


@pytest.fixture
def dash(tmp_path: Path) -> Iterator[tuple[Dashboard, LabService]]:
    with dashboard_on_fake_lab(tmp_path / "runs") as running:
        yield running


def test_fit_shows_the_candidate_beside_the_configured_threshold_and_applies_it(dash) -> None:  # noqa: ANN001
    dashboard, service = dash
    configured = service.config.imaging.threshold
    assert dashboard.b_apply_threshold.disabled
    dashboard._fit_threshold()
    fit = service.calibrations()[-1]
    assert fit["kind"] == "threshold" and not fit["applied"]
    assert f"fitted: {fit['threshold']:.1f} counts" in dashboard.h_calibration.content
    assert f"configured: {configured:.1f} counts" in dashboard.h_calibration.content
    assert service.config.imaging.threshold == configured  # fitting applies nothing
    assert not dashboard.b_apply_threshold.disabled
    dashboard._apply_threshold()
    assert service.config.imaging.threshold == round(fit["threshold"], 3)
    assert dashboard.b_apply_threshold.disabled
