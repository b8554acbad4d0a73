"""Property test of the API against its own /openapi.json (schemathesis): no 5xx, no undocumented status code,
responses that match their schemas. Bounded examples keep it to a few seconds; runs on the stand-in engine,
so generated configurations are applied instantly instead of compiling kernels. The app has a token, so the
checks also confirm that every mutating route refuses a request without it; a second pass sends every
generated request with no token at all (commands: 401; reads: answered, never 401 or 5xx). The statistics and
run-file routes are checked to be in the schema, each run route is validated on a real run file (with a kept
frame), and run names are fuzzed with hostile strings: always a 4xx, never a 5xx or a file from outside the
runs directory.

One check is relaxed, for the configuration routes only: a schema-valid configuration may still be refused
(422), because JSON Schema cannot say the cross-field rules a configuration must obey (tones on the slot
grid, traps inside the camera ROI, different trigger lines, ...). Every refusal is still checked to be a
documented status with a documented body; wrong types and out-of-range values must be refused."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

schemathesis = pytest.importorskip("schemathesis")  # the imports below (E402) need it, or the module is skipped
from fastapi.routing import APIRoute  # noqa: E402
from fastapi.testclient import TestClient  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from schemathesis.checks import positive_data_acceptance  # noqa: E402

from engine.engine import EngineThread  # noqa: E402
from server.app import create_app  # noqa: E402
from server.routes import runs, stats  # noqa: E402
from server.runstore import RUN_NAME, FrameKeeping, RunStore  # noqa: E402
from server.service import LabService  # noqa: E402
from server_fakes import FakeEngine, example_config  # noqa: E402

_root = Path(__import__("tempfile").mkdtemp(prefix="llrs-schema-"))
_runs = _root / "runs"
SECRET = b"outside the runs directory"  # a file beside the runs directory that no route may serve
(_root / "secret.h5").write_bytes(SECRET)
_service = LabService(
    engine_thread=EngineThread(lambda: FakeEngine(example_config(), keep_images=True)),  # type: ignore[arg-type, return-value]  # a fake engine
    store=RunStore(_runs, frames=FrameKeeping(every_nth_shot=1)),
    pause_s=0.01,
)
TOKEN = "schema-token"
_app = create_app(service=_service, token=TOKEN)
schema = schemathesis.openapi.from_asgi("/openapi.json", _app)


@pytest.fixture(scope="module", autouse=True)
def _started() -> object:
    _service.start()
    _service.shot()  # so that /api/shots/{id} and its image have something to find
    _service.run_store.flush()  # type: ignore[union-attr]  # and a run file, with the shot's frames
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


#: Read routes that a request without a token may use; everything else in the schema is a command.
_READS = {"GET", "HEAD"}


@schema.parametrize()
@settings(max_examples=5, deadline=None, suppress_health_check=list(HealthCheck))
def test_without_a_token_commands_are_refused_and_reads_answered(case: schemathesis.Case) -> None:
    response = case.call()  # no Authorization header at all
    if case.method.upper() != case.operation.method.upper():  # schemathesis also tries methods a path lacks
        assert response.status_code in (401, 405), (case.method, case.path, response.status_code)
    elif case.method.upper() in _READS:
        assert response.status_code != 401 and response.status_code < 500, (case.path, response.status_code)
    else:
        assert response.status_code == 401, (case.method, case.path, response.status_code)


def test_every_stats_and_runs_route_is_in_the_checked_schema() -> None:
    served = {  # every route of the statistics and run-file routers
        (method, route.path)
        for router in (stats.reads, stats.commands, runs.reads)
        for route in router.routes
        if isinstance(route, APIRoute)
        for method in route.methods or ()
    }
    # the operations schemathesis parametrizes the tests above with: every (path, method) of the loaded schema
    checked = {(method.upper(), path) for path, item in schema.raw_schema["paths"].items() for method in item}
    assert {
        ("GET", "/api/stats"), ("POST", "/api/stats/reset"), ("GET", "/api/runs"), ("GET", "/api/runs/{name}"),
        ("GET", "/api/runs/{name}/shots/{index}"), ("GET", "/api/runs/{name}/shots/{index}/frames/{cycle}"),
    } <= served <= checked


def _run_name() -> str:
    runs = _service.run_store.runs()  # type: ignore[union-attr]  # built with one
    assert runs, "the fixture's shot was not written to a run file"
    return str(runs[0]["name"])


@pytest.mark.parametrize(
    ("path", "parameters"),
    [
        ("/api/runs/{name}", {}),
        ("/api/runs/{name}/shots/{index}", {"index": 0}),
        ("/api/runs/{name}/shots/{index}/frames/{cycle}", {"index": 0, "cycle": 0}),
        ("/api/runs/{name}/shots/{index}/frames/{cycle}", {"index": 0, "cycle": 99}),  # no such frame: 404
    ],
)
def test_run_routes_conform_on_a_real_run_file(path: str, parameters: dict[str, int]) -> None:
    """The run routes as generated cases cannot reach them (a name that exists), validated against the schema."""
    case = schema[path]["GET"].Case(path_parameters={"name": _run_name(), **parameters})
    response = case.call_and_validate()
    assert response.status_code == (404 if parameters.get("cycle") == 99 else 200)


HOSTILE = [
    "../secret.h5", "..%2Fsecret.h5", "%2e%2e%2fsecret.h5", "..", ".", "/etc/passwd", "secret.h5",
    "20260101-120000-0.h5/../../secret.h5", "20260101-120000-0.h5\x00", "..\\secret.h5", "~/secret.h5",
    "20260101-120000-0.h5 ", "２0260101-120000-0.h5", "20260101-120000-0.h5.lnk", "a" * 5000,
]


def _encoded(name: str) -> str:
    """Every byte percent-encoded, dots too: the name reaches the server as sent, not as a client's URL
    normalization would rewrite it (``/api/runs/..`` is ``/api``)."""
    return "".join(f"%{byte:02X}" for byte in name.encode())


@given(name=st.one_of(st.sampled_from(HOSTILE), st.text(min_size=1, max_size=80)))
@settings(max_examples=150, deadline=None, suppress_health_check=list(HealthCheck))
def test_hostile_run_names_get_4xx_and_nothing_outside_the_runs_directory(name: str) -> None:
    real = _run_name()
    with TestClient(_app) as client:
        for route in ("", "/shots/0", "/shots/0/frames/0"):
            r = client.get(f"/api/runs/{_encoded(name)}{route}")
            assert r.status_code < 500, (name, route, r.status_code)
            assert SECRET not in r.content
            if name != real:
                assert 400 <= r.status_code < 500, (name, route, r.status_code)
    assert re.fullmatch(RUN_NAME, real)


def test_a_run_named_slash_is_refused_not_redirected_to_the_listing() -> None:
    with TestClient(_app) as client:
        r = client.get("/api/runs/%2F", follow_redirects=False)
        assert r.status_code == 404, (r.status_code, r.headers.get("location"))
