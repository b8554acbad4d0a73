"""Property test of the API against its own /openapi.json (schemathesis): no 5xx, no undocumented status code,
responses that match their schemas. Bounded examples keep it to a few seconds; runs on the stand-in engine,
so generated configurations are applied instantly instead of compiling kernels. The app has a token, so the
checks also confirm that every mutating route refuses a request without it.

One check is relaxed, for the configuration routes only: a schema-valid configuration may still be refused
(422), because JSON Schema cannot say the cross-field rules a configuration must obey (tones on the slot
grid, traps inside the camera ROI, different trigger lines, ...). Every refusal is still checked to be a
documented status with a documented body; wrong types and out-of-range values must be refused."""

from __future__ import annotations

from pathlib import Path

import pytest

schemathesis = pytest.importorskip("schemathesis")  # the imports below (E402) need it, or the module is skipped
from hypothesis import HealthCheck, settings  # noqa: E402
from schemathesis.checks import positive_data_acceptance  # noqa: E402

from engine.engine import EngineThread  # noqa: E402
from server.app import create_app  # noqa: E402
from server.runstore import RunStore  # noqa: E402
from server.service import LabService  # noqa: E402
from server_fakes import FakeEngine, example_config  # noqa: E402

_runs = Path(__import__("tempfile").mkdtemp(prefix="llrs-schema-"))
_service = LabService(
    engine_thread=EngineThread(lambda: FakeEngine(example_config(), keep_images=True)),  # type: ignore[arg-type, return-value]  # a fake engine
    store=RunStore(_runs),
    pause_s=0.01,
)
TOKEN = "schema-token"
_app = create_app(service=_service, token=TOKEN)
schema = schemathesis.openapi.from_asgi("/openapi.json", _app)


@pytest.fixture(scope="module", autouse=True)
def _started() -> object:
    _service.start()
    _service.shot()  # so that /api/shots/{id} and its image have something to find
    yield
    _service.close()


@schema.parametrize()
@settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck))
def test_api_conforms_to_its_schema(case: schemathesis.Case) -> None:
    # configs and overrides have cross-field rules; a shot-file path is only valid if such a file exists
    cross_field_rules = case.path in ("/api/config", "/api/shots", "/api/labscript")
    case.call_and_validate(
        headers={"Authorization": f"Bearer {TOKEN}"},
        excluded_checks=[positive_data_acceptance] if cross_field_rules else [],
    )
