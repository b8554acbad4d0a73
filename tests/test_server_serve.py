"""``llrs serve`` without a browser: the bind rule, argument handling and clean errors."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from server.serve import is_loopback

ROOT = Path(__file__).resolve().parent.parent


@pytest.mark.parametrize(
    ("host", "loopback"),
    [("127.0.0.1", True), ("127.1.2.3", True), ("localhost", True), ("::1", True), ("[::1]", True),
     ("0.0.0.0", False), ("::", False), ("192.168.1.20", False), ("lab-pc.example", False)],
)
def test_is_loopback(host: str, loopback: bool) -> None:
    assert is_loopback(host) is loopback


def _serve(*args: str, token: str | None = None) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "LLRS_TOKEN"}
    if token is not None:
        env["LLRS_TOKEN"] = token
    return subprocess.run(
        [sys.executable, "-m", "server.cli", "serve", *args], cwd=ROOT, env=env, capture_output=True, text=True,
        timeout=120,
    )


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.0.2.1"])
def test_refuses_a_reachable_address_without_a_token(host: str) -> None:
    r = _serve("--host", host, "--port", "0")
    assert r.returncode == 2, r.stdout + r.stderr
    assert "refusing to bind" in r.stderr and "LLRS_TOKEN" in r.stderr
    assert "starting the engine" not in r.stdout  # refused before anything started


def test_an_empty_token_does_not_count() -> None:
    r = _serve("--host", "0.0.0.0", "--port", "0", token="")
    assert r.returncode == 2 and "refusing to bind" in r.stderr


def test_bad_config_is_a_clear_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("sim: {loading_probability: 3}\n")
    r = _serve("--config", str(bad), "--port", "0")
    assert r.returncode == 2 and "sim.loading_probability" in r.stderr


@pytest.mark.parametrize(
    ("value", "message"), [("4096", "this process may use cores"), ("fast", "core number, 'auto' or 'none'")]
)
def test_bad_engine_core_is_a_clear_error(value: str, message: str) -> None:
    r = _serve("--engine-cpu", value, "--port", "0")
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert "starting the engine" not in r.stdout


def test_refuses_a_reachable_dashboard_without_a_token() -> None:
    r = _serve("--dashboard-host", "0.0.0.0", "--port", "0")
    assert r.returncode == 2 and "refusing to bind the dashboard" in r.stderr
    assert "starting the engine" not in r.stdout
