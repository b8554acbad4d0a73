"""The server's front page: links to the dashboard, the API docs and the status."""

from __future__ import annotations

import html

from fastapi import APIRouter, Request
from fastapi.responses import HTMLResponse

__all__ = ["reads"]

reads = APIRouter()


@reads.get("/", response_class=HTMLResponse, summary="Links to the dashboard, the API docs and the status")
def index(request: Request) -> str:
    dashboard_port = request.app.state.dashboard_port
    host = request.url.hostname or "127.0.0.1"
    dash = (
        f'<li><a id="dashboard" href="http://{html.escape(host)}:{dashboard_port}/">dashboard</a> '
        "(live atom map, timings, controls)</li>"
        if dashboard_port
        else "<li>dashboard: not running</li>"
    )
    return (
        "<!doctype html><html><head><meta charset='utf-8'><title>LLRS lab server</title></head><body>"
        f"<h1>LLRS lab server</h1><ul>{dash}<li><a href='/docs'>API docs</a> "
        "(<a href='/openapi.json'>openapi.json</a>)</li><li><a href='/api/status'>status</a></li>"
        "<li>live cycles: websocket <code>/api/live</code></li></ul></body></html>"
    )
