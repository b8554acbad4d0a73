"""The dashboard behind the token, in headless Chromium against a real ``llrs serve`` with ``LLRS_TOKEN``: a
browser that has not logged in sees the lab but its buttons change nothing (as the REST API answers 401);
after logging in with the token in its own field, the same button runs a shot."""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from test_dashboard_browser import CHROMIUM, CHROMIUM_ARGS, llrs_serve

if not Path(CHROMIUM).exists():
    pytest.skip(f"no Chromium at {CHROMIUM}", allow_module_level=True)
sync_playwright = pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra").sync_playwright

TOKEN = "dashboard-token"


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, str]]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "LLRS_TOKEN": TOKEN}
    runs = str(tmp_path_factory.mktemp("runs"))
    with llrs_serve("--idle", "--engine", "thread", "--runs-dir", runs, env=env) as running:
        yield running.api, running.dashboard


def token_field(page: object) -> object:
    """The login panel's text field (viser's label does not name its input, so find it beside the label)."""
    return page.locator(  # type: ignore[attr-defined]
        "xpath=//label[text()='Token']/ancestor::div[contains(@class, 'mantine-Flex-root')][1]//input"
    )


def shots_done(api: str) -> int:
    return httpx.get(api + "/api/status").json()["shots_done"]


def test_dashboard_acts_only_after_logging_in_with_the_token(served: tuple[str, str]) -> None:
    api, dashboard = served
    assert httpx.post(api + "/api/shots").status_code == 401
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1440, "height": 900})
            page.goto(dashboard)
            page.wait_for_selector("#lab-status", timeout=60_000)
            page.get_by_role("button", name="One shot").click()
            page.get_by_role("button", name="Run continuously").click()
            page.get_by_text("read-only: log in").wait_for(timeout=20_000)
            assert shots_done(api) == 0 and httpx.get(api + "/api/status").json()["state"] == "idle"

            token_field(page).fill("not the token")
            page.get_by_role("button", name="Log in").click()
            page.get_by_text("wrong token").wait_for(timeout=20_000)
            page.get_by_role("button", name="One shot").click()
            page.wait_for_timeout(1000)
            assert shots_done(api) == 0

            token_field(page).fill(TOKEN)
            page.get_by_role("button", name="Log in").click()
            page.get_by_text("logged in").wait_for(timeout=20_000)
            page.get_by_role("button", name="One shot").click()
            page.wait_for_selector("#lab-status[data-shots='1']", timeout=30_000)
            assert shots_done(api) == 1
        finally:
            browser.close()
