"""What stands between the network and the lab service: the bearer token, trusted hosts and origins, JSON
bodies of bounded size.

``RequestGuard`` is an ASGI middleware that looks at a request's headers before anything reads its body:

- a ``Host`` header not in ``trusted_hosts`` (when given) is refused (400): without a token the server binds
  to loopback, and a page on another site cannot reach it through a DNS name it controls;
- an ``Origin`` header that is neither this server's own origin nor one of ``cors_origins`` is refused (403)
  on every mutating request and on websockets: a page from another origin cannot start shots or change
  the configuration, even with no token set;
- with a token, a mutating request without ``Authorization: Bearer <token>`` is refused (401) before its
  body is read, so an unauthenticated client cannot make the server buffer or parse anything;
- a mutating request with a body must say ``Content-Type: application/json`` (415; a ``text/plain`` body is
  what a cross-site form can send without asking), and the body may hold at most ``max_body_bytes`` (413).

``require_token`` is the same check as a FastAPI dependency on the mutating routes, so the OpenAPI document
states the requirement and a route stays protected even when served without the guard.
"""

from __future__ import annotations

import hmac
import json
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Annotated, Any
from urllib.parse import urlsplit

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

__all__ = ["LOOPBACK_HOSTS", "MUTATING", "RequestGuard", "bearer", "require_token", "token_matches"]

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]

MUTATING = frozenset({"POST", "PUT", "PATCH", "DELETE"})

#: Host names a loopback-only server answers to.
LOOPBACK_HOSTS = ("127.0.0.1", "localhost", "::1")

bearer = HTTPBearer(auto_error=False, description="LLRS_TOKEN: required on every mutating route")


def token_matches(authorization: str | None, token: str) -> bool:
    """True if an ``Authorization`` header value carries ``token`` as a bearer token (constant-time)."""
    scheme, _, credentials = (authorization or "").partition(" ")
    return scheme.lower() == "bearer" and hmac.compare_digest(credentials.strip().encode(), token.encode())


def require_token(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> None:
    """FastAPI dependency of every mutating route: 401 unless the app's token is presented."""
    token: str | None = request.app.state.token
    if token is None:
        return
    if credentials is None or not hmac.compare_digest(credentials.credentials.encode(), token.encode()):
        raise HTTPException(401, detail="missing or wrong bearer token", headers={"WWW-Authenticate": "Bearer"})


def _host_name(host_header: str) -> str:
    """The host of a ``Host`` header, without port and IPv6 brackets, lower case."""
    host = host_header.strip().lower()
    if host.startswith("["):
        return host[1 : host.find("]")] if "]" in host else host
    return host.rsplit(":", 1)[0] if host.count(":") == 1 else host


class RequestGuard:
    """ASGI middleware: hosts, origins, token, content type and body size, checked on headers (see module)."""

    def __init__(
        self,
        app: Callable[[Scope, Receive, Send], Awaitable[None]],
        *,
        token: str | None,
        trusted_hosts: tuple[str, ...] | None,
        cors_origins: tuple[str, ...],
        max_body_bytes: int,
    ) -> None:
        self.app = app
        self.token = token
        self.trusted_hosts = {h.lower() for h in trusted_hosts} if trusted_hosts is not None else None
        self.cors_origins = {o.rstrip("/").lower() for o in cors_origins}
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        host = headers.get("host", "")
        if self.trusted_hosts is not None and _host_name(host) not in self.trusted_hosts:
            await self._refuse(
                scope, send, 400, f"untrusted Host header; this server answers to {sorted(self.trusted_hosts)}"
            )
            return
        mutating = scope["type"] == "websocket" or scope["method"] in MUTATING
        origin = headers.get("origin")
        if mutating and origin is not None and not self._origin_ok(origin, host):
            await self._refuse(
                scope, send, 403, "cross-origin request refused: start llrs serve with --cors-origin to allow an origin"
            )
            return
        if scope["type"] == "websocket" or scope["method"] not in MUTATING:
            await self.app(scope, receive, send)
            return
        if self.token is not None and not token_matches(headers.get("authorization"), self.token):
            await self._refuse(scope, send, 401, "missing or wrong bearer token", [(b"www-authenticate", b"Bearer")])
            return
        length = headers.get("content-length")
        has_body = "transfer-encoding" in headers or (length is not None and length.strip() != "0")
        if has_body and headers.get("content-type", "").split(";")[0].strip().lower() != "application/json":
            await self._refuse(scope, send, 415, "a request body must be JSON (Content-Type: application/json)")
            return
        if length is not None and (not length.strip().isdigit() or int(length) > self.max_body_bytes):
            await self._refuse(scope, send, 413, f"request body over {self.max_body_bytes} bytes")
            return
        body = bytearray()
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            body += message.get("body", b"")
            if len(body) > self.max_body_bytes:
                await self._refuse(scope, send, 413, f"request body over {self.max_body_bytes} bytes")
                return
            if not message.get("more_body", False):
                break
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": bytes(body), "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    def _origin_ok(self, origin: str, host: str) -> bool:
        origin = origin.rstrip("/").lower()
        if origin in self.cors_origins:
            return True
        parts = urlsplit(origin)
        return parts.scheme in ("http", "https") and parts.netloc == host.strip().lower()

    @staticmethod
    async def _refuse(
        scope: Scope, send: Send, status: int, detail: str, extra: list[tuple[bytes, bytes]] | None = None
    ) -> None:
        if scope["type"] == "websocket":  # before the handshake is accepted: an HTTP 403 to the client
            await send({"type": "websocket.close", "code": 1008, "reason": detail[:120]})
            return
        body = json.dumps({"detail": detail}).encode()
        headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()), *(extra or [])]
        await send({"type": "http.response.start", "status": status, "headers": headers})
        await send({"type": "http.response.body", "body": body})
