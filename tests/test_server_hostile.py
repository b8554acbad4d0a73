"""A hostile client against a real ``llrs serve`` (a subprocess with a token, on 127.0.0.1 only): garbage,
oversize and deeply nested bodies, foreign hosts and origins, 2000 websocket connections, special files as
paths. Every attack gets a 4xx (or a refused handshake); afterwards the server answers ``/api/status``
promptly, holds about the memory it started with, and runs the configuration it started with."""

from __future__ import annotations

import asyncio
import os
import resource
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
TOKEN = "hostile-test-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
WEBSOCKETS = 2000


def rss_bytes(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS")


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, subprocess.Popen[str], Path]]:
    if not Path("/proc/self/status").exists():
        pytest.skip("needs /proc to measure memory")
    tmp = tmp_path_factory.mktemp("hostile")
    (tmp / "tones").mkdir()
    (tmp / "shots").mkdir()
    os.mkfifo(tmp / "tones" / "fifo.csv")
    (tmp / "tones" / "header.csv").write_text("secret-header-cell,nu,phi\n1,2,3\n")
    (tmp / "tones" / "cells.csv").write_text("alpha,nu,phi\n" + "secret-cell,80e6,0\n" * 64)
    (tmp / "tones" / "long-line.csv").write_text("alpha,nu,phi\n" + "9" * 200_000 + "\n")
    os.mkfifo(tmp / "shots" / "fifo.h5")
    env = dict(os.environ, LLRS_TOKEN=TOKEN)
    proc = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "serve", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
         "--idle", "--engine", "thread", "--runs-dir", str(tmp / "runs"), "--tone-dir", str(tmp / "tones"),
         "--shot-dir", str(tmp / "shots"), "--trusted-host", "localhost"],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    url = None
    assert proc.stdout is not None
    for line in proc.stdout:
        if line.strip().startswith("API"):
            url = line.split()[1].rstrip("/")
        if "Ctrl-C stops the server" in line:
            break
    assert url is not None, "llrs serve did not start"
    try:
        yield url, proc, tmp
    finally:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()


def raw_request(url: str, head: str, body: bytes = b"") -> int:
    """Send ``head`` (request line and headers) and ``body`` on a plain socket; the response's status code."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=10) as s:
        s.sendall(head.encode() + b"\r\n" + body)
        return int(s.recv(4096).split(b" ", 2)[1])


async def open_websockets(url: str, n: int) -> list[int]:
    """Open ``n`` websocket handshakes to /api/live at once and hold them; the status line of each."""
    host, port = url.removeprefix("http://").split(":")
    handshake = (
        f"GET /api/live HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
        "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n"
    ).encode()

    async def one() -> tuple[int, asyncio.StreamWriter | None]:
        try:
            reader, writer = await asyncio.open_connection(host, int(port))
            writer.write(handshake)
            line = await asyncio.wait_for(reader.readline(), 20)
            return int(line.split(b" ")[1]), writer
        except (OSError, TimeoutError, IndexError, ValueError):
            return 0, None

    results = await asyncio.gather(*(one() for _ in range(n)))
    await asyncio.sleep(0.5)
    for _, writer in results:
        if writer is not None:
            writer.close()
    return [status for status, _ in results]


def status_latencies_s(client: httpx.Client, n: int = 100) -> list[float]:
    latencies = []
    for _ in range(n):
        t0 = time.perf_counter()
        assert client.get("/api/status").status_code == 200
        latencies.append(time.perf_counter() - t0)
    return latencies


def test_hostile_client(server: tuple[str, subprocess.Popen[str], Path]) -> None:
    url, proc, tmp = server
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < WEBSOCKETS + 200:
        resource.setrlimit(resource.RLIMIT_NOFILE, (min(hard, WEBSOCKETS + 500), hard))
    with httpx.Client(base_url=url, timeout=30) as c:
        config = c.get("/api/config").json()
        for _ in range(20):  # warm the server's paths before taking its memory
            c.get("/api/status")
        start_rss = rss_bytes(proc.pid)
        before_s = status_latencies_s(c)

        json_type = {"Content-Type": "application/json"}
        json_auth = {**AUTH, **json_type}
        # garbage, without and with the token
        assert c.patch("/api/config", content=b"\x00garbage", headers=json_type).status_code == 401
        assert c.patch("/api/config", content=b"\x00garbage", headers=json_auth).status_code in (400, 422)
        assert c.put("/api/config", content=b"[1, 2", headers=json_auth).status_code == 400
        # oversize: refused on the headers, before a byte of the body is read
        assert raw_request(url, "PATCH /api/config HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
                           "Content-Length: 50000000\r\n") == 401
        assert raw_request(url, f"PATCH /api/config HTTP/1.1\r\nHost: 127.0.0.1\r\nAuthorization: Bearer {TOKEN}\r\n"
                           "Content-Type: application/json\r\nContent-Length: 50000000\r\n") == 413
        big = b'{"name": "' + b"x" * 5_000_000 + b'"}'
        assert c.patch("/api/config", content=big, headers=json_auth).status_code == 413
        # deeply nested
        nested = b'{"a":' * 50_000 + b"1" + b"}" * 50_000
        for method in ("PUT", "PATCH"):
            r = c.request(method, "/api/config", content=nested, headers=json_auth)
            assert 400 <= r.status_code < 500, r.text
        # foreign hosts and origins, text/plain bodies
        assert c.get("/api/status", headers={"Host": "evil.example"}).status_code == 400
        assert c.post("/api/shots", headers={**AUTH, "Origin": "http://evil.example"}).status_code == 403
        assert c.put("/api/config", content=b"{}", headers={**AUTH, "Content-Type": "text/plain"}).status_code == 415
        # special files as paths
        for csv in (
            "/proc/self/environ", "/dev/zero", "fifo.csv", "/etc/passwd", "header.csv", "cells.csv", "long-line.csv"
        ):
            r = c.patch("/api/config", json={"array": {"x_tones": {"csv": csv}}}, headers=AUTH)
            assert r.status_code == 422, r.text
            assert not any(leak in r.text for leak in (TOKEN, "root:", "secret", "999")), r.text
        for path in ("fifo.h5", "/dev/zero", "/proc/self/environ"):
            r = c.post("/api/labscript", json={"path": path}, headers=AUTH)
            assert 400 <= r.status_code < 500 and TOKEN not in r.text, r.text
        # unbounded numbers
        huge = ({"awg": {"upload_jitter_s": 1e300}}, {"camera": {"read_noise_e": 1e300}}, {"name": "x" * 100_000})
        for patch in huge:
            assert c.patch("/api/config", json=patch, headers=AUTH).status_code == 422

        # 2000 websocket connections at once: a few subscribe, the rest are refused, none hangs the server
        statuses = asyncio.run(open_websockets(url, WEBSOCKETS))
        assert statuses.count(101) <= 64
        assert all(s in (101, 403, 503) for s in statuses), sorted(set(statuses))

        # not slowed by the attacks: against the same server's own figure before them (a fixed bound in
        # seconds measures the machine's load, not the server), with 20 ms of slack for scheduler noise
        after_s = status_latencies_s(c)
        median_before_s, median_after_s = float(np.median(before_s)), float(np.median(after_s))
        p99_s = float(np.percentile(after_s, 99))
        assert median_after_s < 2 * median_before_s + 0.02, (
            f"/api/status median {median_after_s * 1e3:.1f} ms after the attacks, {median_before_s * 1e3:.1f} before"
        )
        grown = rss_bytes(proc.pid) - start_rss
        assert grown < 50 * 2**20, f"the server grew by {grown / 2**20:.0f} MB"
        assert c.get("/api/config").json() == config
        assert proc.poll() is None
        print(f"hostile client: {statuses.count(101)} websockets subscribed of {WEBSOCKETS}; /api/status p99 "
              f"{p99_s * 1e3:.1f} ms afterwards; memory {grown / 2**20:+.1f} MB")
