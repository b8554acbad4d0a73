"""Live cycles over a websocket, each subscriber reading its own bounded queue (``server.hub``)."""

from __future__ import annotations

import asyncio
import json

import numpy as np
from fastapi import APIRouter, WebSocket

from server.hub import cycle_messages

__all__ = ["reads"]

reads = APIRouter()


@reads.websocket("/api/live")
async def live(ws: WebSocket) -> None:
    """Per-cycle JSON messages (``server.models.LiveCycle``): the last shot at once, then every new one.

    Send ``{"images": true}`` to also get camera frames: after a cycle's JSON message, when the server holds
    that cycle's frame (the final frame of every shot; every cycle's if images are kept), a JSON header
    ``{"type": "image", "shot_id", "cycle", "shape": [h, w], "dtype": "<u2"}`` and then one binary message
    with the raw little-endian uint16 pixels, row by row. ``{"images": false}`` stops them.

    At most ``app.state.max_live`` subscribers at once: the next one is refused (HTTP 403 at the handshake)
    until one leaves, so idle connections cannot pile up.
    """
    hub = ws.app.state.hub
    service = ws.app.state.service
    if hub.subscribers >= ws.app.state.max_live:
        await ws.close(code=1013, reason="too many live subscribers; try again later")
        return
    queue = hub.subscribe()
    try:
        await ws.accept()
    except BaseException:
        hub.unsubscribe(queue)
        raise
    want_images = False
    last = service.last_record()
    if last is not None:
        for message in cycle_messages(last)[-queue.maxsize :]:
            queue.put_nowait(message)

    async def pump() -> None:
        while True:
            message = await queue.get()
            await ws.send_json(message)
            if want_images:
                frame = service.frame(message["shot_id"], message["cycle"])
                if frame is not None:
                    pixels = np.ascontiguousarray(frame, dtype="<u2")
                    await ws.send_json(
                        {"type": "image", "shot_id": message["shot_id"], "cycle": message["cycle"],
                         "shape": list(pixels.shape), "dtype": "<u2"}
                    )
                    await ws.send_bytes(pixels.tobytes())

    sender = asyncio.create_task(pump())
    try:
        while (event := await ws.receive())["type"] != "websocket.disconnect":
            text = event.get("text") or "null"
            try:
                request = json.loads(text) if len(text) <= 1024 else None
            except (ValueError, RecursionError):
                request = None
            if isinstance(request, dict) and isinstance(request.get("images"), bool):
                want_images = request["images"]
    finally:
        sender.cancel()
        hub.unsubscribe(queue)
