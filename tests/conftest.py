"""Fixtures shared by the test files: a lossless configuration, a lab server reached over HTTP, and a wait
on a condition (instead of a fixed ``sleep``, which is either too short on a loaded machine or wasted time).

Plain helpers that are not fixtures live beside the fakes (``sim_signals.py``, ``server_fakes.py``).
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

from engine.config import SystemConfig, load_config

if TYPE_CHECKING:
    from fastapi.testclient import TestClient

    from server.service import LabService

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Give schemathesis's tests one node id per API operation (``test_x[GET /api/status]``).

    pytest 9.2 builds a test's id from its ``originalname`` and parametrize call, and schemathesis 4 passes the
    test function's bare name there, so every operation of ``test_server_schema.py`` gets the same id. pytest
    alone still runs them all, but pytest-xdist schedules by id and would run one operation per test and drop
    the rest; unique ids also let ``-k``, ``--lf`` and the failure report name the operation."""
    counts = Counter(item.nodeid for item in items)
    for item in items:
        if counts[item.nodeid] > 1 and item.parent is not None and "[" in item.name:
            item._id = type(item._id).parse(f"{item.parent.nodeid}::{item.name}")  # pytest 9.2: a structured NodeId

#: Every fault the simulated lab injects (``sim.faults``) and words the shot's fault reason then contains,
#: for the engine's fault tests and the server's.
INJECTED_FAULTS = [
    ({"camera": "timeout"}, "camera: no frame within"),
    ({"camera": "corrupt"}, "arrived corrupt"),
    ({"awg_upload": "fail"}, "injected upload failure"),
    ({"solver": "exception"}, "InjectedSolverFault"),
]


def lossless(config: SystemConfig, **sim: object) -> SystemConfig:
    """``config`` with the simulated lab's losses off (and any other ``sim`` fields given), so that a shot's
    outcome depends only on the engine: every atom a plan moves arrives."""
    return config.model_copy(update={"sim": config.sim.model_copy(update={"lossless": True, **sim})})


@pytest.fixture(scope="session")
def lossless_chain() -> SystemConfig:
    """The paper's 1x64 -> 32 chain (``examples/chain-1x64.yaml``), lossless; ``lossless(lossless_chain,
    seed=...)`` for other simulator settings. Session-scoped, so module-scoped fixtures can build on it."""
    return lossless(load_config(EXAMPLES / "chain-1x64.yaml"))


@pytest.fixture
def lab_server() -> Callable[[SystemConfig], AbstractContextManager[tuple[LabService, TestClient]]]:
    """``with lab_server(config) as (service, client):`` the lab service on the simulated lab, the engine in
    a process of its own as ``llrs serve`` runs it, behind the FastAPI app, reached through ``TestClient``
    (HTTP without a socket). Closed, engine process included, when the block ends."""

    # deferred on purpose: the web stack (about a second to import) loads only for the tests that serve
    from fastapi.testclient import TestClient

    from server.app import create_app
    from server.serve import engine_host_factory
    from server.service import LabService

    @contextmanager
    def serve(config: SystemConfig) -> Iterator[tuple[LabService, TestClient]]:
        factory = engine_host_factory(in_process=True, cpu=None)
        service = LabService(engine_thread=factory(config), engine_factory=factory, config=config, pause_s=0.0)
        service.start()
        try:
            with TestClient(create_app(service=service)) as client:
                yield service, client
        finally:
            service.close()

    return serve


def wait_until(condition: Callable[[], object], *, timeout_s: float = 10.0, what: str = "the condition") -> None:
    """Return as soon as ``condition()`` is true; fail naming ``what`` after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"{what} did not happen within {timeout_s:g} s")
        time.sleep(0.005)


@pytest.fixture(name="wait_until")
def wait_until_fixture() -> Callable[..., None]:
    """``wait_until(condition, timeout_s=10, what="...")``: poll a condition instead of sleeping a fixed time."""
    return wait_until
