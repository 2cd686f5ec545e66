"""The checks made before a request body is read: the API key on /v1 routes and the upload size.

FastAPI reads (and spools to disk) a whole multipart body before it runs any route code or
dependency, so both checks live in this plain ASGI middleware instead: a request without the key
is refused before its body is read, a declared ``Content-Length`` over the limit is refused at
once, and a body without one (chunked) is counted as it streams in and cut off with 413 as soon
as it passes the limit.
"""

from __future__ import annotations

import json
import secrets

from starlette.datastructures import Headers
from starlette.types import ASGIApp, Message, Receive, Scope, Send


class BodyTooLarge(Exception):
    """Raised into the app when the streamed body passes the limit."""


class RequestGuard:
    def __init__(self, app: ASGIApp, *, max_body_bytes: int, api_key: str | None = None):
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.api_key = api_key.encode() if api_key else None

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = Headers(scope=scope)
        if self.api_key and (scope["path"] == "/v1" or scope["path"].startswith("/v1/")):
            if not self._authorized(headers.get("authorization", "")):
                detail = "missing or wrong API key: send the header 'Authorization: Bearer <key>'"
                return await _answer(send, 401, detail, [(b"www-authenticate", b"Bearer")])
        # A 413 leaves the rest of the body unread, so the connection cannot be reused.
        close = [(b"connection", b"close")]
        declared = headers.get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.max_body_bytes:
            return await _answer(send, 413, self._too_large(), close)

        received = 0
        too_large = False

        async def counting_receive() -> Message:
            nonlocal received, too_large
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body_bytes:
                    too_large = True
                    raise BodyTooLarge()
            return message

        async def guarded_send(message: Message) -> None:
            if not too_large:  # the app's own answer to a cut-off body is replaced by the 413
                await send(message)

        try:
            await self.app(scope, counting_receive, guarded_send)
        except Exception:
            if not too_large:
                raise
        if too_large:
            await _answer(send, 413, self._too_large(), close)

    def _authorized(self, header: str) -> bool:
        scheme, _, token = header.partition(" ")
        expected = self.api_key or b""
        return scheme.lower() == "bearer" and secrets.compare_digest(token.strip().encode(), expected)

    def _too_large(self) -> str:
        limit = self.max_body_bytes
        return f"the upload is larger than the limit of {limit} bytes ({limit / 2**20:g} MiB)"


async def _answer(send: Send, status: int, detail: str, headers: list[tuple[bytes, bytes]]) -> None:
    """Send a complete JSON error response ``{"detail": ...}``."""
    body = json.dumps({"detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                *headers,
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})
