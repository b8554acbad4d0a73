"""The live-data hub: the engine thread publishes, each websocket client reads its own bounded queue.

The engine must never wait for a browser. ``publish`` is called on the engine thread and only schedules work
on the server's event loop (``loop.call_soon_threadsafe``); there every subscriber's ``asyncio.Queue`` gets the
messages, and a full queue drops its oldest message, so a stalled client loses old cycles instead of slowing
anyone down.
"""

from __future__ import annotations

import asyncio
from typing import Any

from engine.records import ShotRecord
from server.models import LiveCycle

__all__ = ["LiveHub", "cycle_messages"]


def cycle_messages(record: ShotRecord) -> list[dict[str, Any]]:
    """A finished shot as one small JSON-ready message per cycle (see ``LiveCycle``)."""
    data = record.to_dict()
    n = len(data["cycles"])
    return [
        LiveCycle(
            shot_id=record.shot_id,
            cycle=c["index"],
            n_cycles=n,
            last=i == n - 1,
            occupancy=c["occupancy"],
            target=data["target"],
            atoms=c["atoms"],
            defects=c["defects"],
            stage_us=c["stage_us"],
            n_slots=c["n_slots"],
            outcome=data["outcome"],
            target_filled=record.lab_report.get("target_filled"),
        ).model_dump(mode="json")
        for i, c in enumerate(data["cycles"])
    ]


class LiveHub:
    """Fan-out of live messages to websocket subscribers on one event loop."""

    def __init__(self, *, maxsize: int = 64) -> None:
        self.maxsize = maxsize
        self._loop: asyncio.AbstractEventLoop | None = None
        self._queues: set[asyncio.Queue[dict[str, Any]]] = set()
        self.dropped = 0

    def bind(self, loop: asyncio.AbstractEventLoop | None) -> None:
        """Attach to the server's loop (lifespan start) or detach (``None``, at shutdown)."""
        self._loop = loop
        if loop is None:
            self._queues.clear()

    def subscribe(self) -> asyncio.Queue[dict[str, Any]]:
        """A new client's queue; call on the loop."""
        q: asyncio.Queue[dict[str, Any]] = asyncio.Queue(maxsize=self.maxsize)
        self._queues.add(q)
        return q

    def unsubscribe(self, q: asyncio.Queue[dict[str, Any]]) -> None:
        self._queues.discard(q)

    @property
    def subscribers(self) -> int:
        return len(self._queues)

    def publish_record(self, record: ShotRecord) -> None:
        """Any thread: hand a finished shot to the loop, which turns it into per-cycle messages."""
        loop = self._loop
        if loop is None or loop.is_closed():
            return
        try:
            loop.call_soon_threadsafe(self._fan_out, record)
        except RuntimeError:  # the loop closed between the check and the call
            pass

    def _fan_out(self, record: ShotRecord) -> None:
        if not self._queues:
            return
        for message in cycle_messages(record):
            for q in self._queues:
                if q.full():
                    q.get_nowait()
                    self.dropped += 1
                q.put_nowait(message)
