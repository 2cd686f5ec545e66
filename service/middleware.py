"""The checks made before and while a request body is read: the API key on /v1 routes, the upload
size, the number of uploads in flight and the time a body may stall.

FastAPI reads (and spools to disk) a whole multipart body before it runs any route code or
dependency, so these checks live in this plain ASGI middleware instead: a request without the key
is refused before its body is read, a declared ``Content-Length`` over the limit is refused at
once, and a body without one (chunked) is counted as it streams in and cut off with 413 as soon
as it passes the limit. A request with a body beyond ``max_uploads`` in flight is refused with
503 before its body is read; a body that sends nothing for ``body_idle_timeout`` seconds is
dropped with 408, so a stalled client cannot hold a slot for ever.
"""

from __future__ import annotations

import asyncio
import json
import secrets

from starlette.datastructures import Headers
from starlette.routing import BaseRoute, Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send


class BodyRefused(Exception):
    """Raised into the app when the streamed body passes the limit or stalls."""


class RequestGuard:
    def __init__(
        self,
        app: ASGIApp,
        *,
        max_body_bytes: int,
        api_key: str | None = None,
        max_uploads: int = 1 << 30,
        body_idle_timeout: float = 30.0,
    ):
        self.app = app
        self.max_body_bytes = max_body_bytes
        self.api_key = api_key.encode() if api_key else None
        self.max_uploads = max_uploads
        self.body_idle_timeout = body_idle_timeout
        self.uploads = 0  # requests with a body in flight (one event loop: no lock needed)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        headers = Headers(scope=scope)
        if self.api_key and (scope["path"] == "/v1" or scope["path"].startswith("/v1/")):
            if not self._authorized(headers.get("authorization", "")):
                detail = "missing or wrong API key: send the header 'Authorization: Bearer <key>'"
                return await _answer(send, 401, detail, [(b"www-authenticate", b"Bearer")])
        # A refusal leaves the rest of the body unread, so the connection cannot be reused.
        close = [(b"connection", b"close")]
        declared = headers.get("content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.max_body_bytes:
            return await _answer(send, 413, self._too_large(), close)
        if not (declared not in (None, "0") or "transfer-encoding" in headers):
            return await self.app(scope, receive, send)  # no body: nothing more to guard
        if self.uploads >= self.max_uploads:
            detail = f"this API process receives {self.max_uploads} uploads already: try again in a moment"
            return await _answer(send, 503, detail, [*close, (b"retry-after", b"2")])

        received = 0
        body_done = False
        refusal: tuple[int, str] | None = None

        async def guarded_receive() -> Message:
            nonlocal received, body_done, refusal
            if body_done:  # the body is complete: later reads wait for a disconnect, unbounded
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), self.body_idle_timeout)
            except TimeoutError:
                refusal = 408, f"the upload sent nothing for {self.body_idle_timeout:g} s: it was dropped"
                raise BodyRefused() from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                body_done = not message.get("more_body", False)
                if received > self.max_body_bytes:
                    refusal = 413, self._too_large()
                    raise BodyRefused()
            return message

        async def guarded_send(message: Message) -> None:
            if refusal is None:  # the app's own answer to a refused body is replaced by the refusal
                await send(message)

        self.uploads += 1
        try:
            await self.app(scope, guarded_receive, guarded_send)
        except Exception:
            if refusal is None:
                raise
        finally:
            self.uploads -= 1
        if refusal is not None:
            await _answer(send, *refusal, close)

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


_METHODS = ("GET", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


class _HeadAnswered(Exception):
    """Raised into the app once a HEAD request's headers are sent: nothing more is wanted of it."""


class HttpMethods:
    """HEAD wherever GET is served (FastAPI routes answer only the methods they declare), and on a
    405 an ``Allow`` that lists every method of the path, not just those of the first route that
    matched it (``/v1/jobs/{id}`` is two routes: GET and DELETE)."""

    def __init__(self, app: ASGIApp, *, routes: list[BaseRoute]):
        self.app = app
        self.routes = routes  # the application's list: routers included later are seen

    def _methods(self, scope: Scope) -> set[str]:
        """The methods some route serves at this path (asked of the routes themselves, which
        FastAPI nests in included routers)."""
        methods = {
            method
            for method in _METHODS
            if any(route.matches({**scope, "method": method})[0] == Match.FULL for route in self.routes)
        }
        return methods | ({"HEAD"} if "GET" in methods else set())

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        head = scope["method"] == "HEAD" and "GET" in self._methods(scope)
        if head:
            scope = {**scope, "method": "GET"}

        async def amended_send(message: Message) -> None:
            methods = (
                self._methods(scope) if message["type"] == "http.response.start" and message["status"] == 405 else None
            )
            if methods:  # (a mount, such as /static, answers its own 405)
                allow = ", ".join(sorted(methods)).encode()
                headers = [(name, value) for name, value in message.get("headers", []) if name.lower() != b"allow"]
                message = {**message, "headers": [*headers, (b"allow", allow)]}
            await send(message)
            if head and message["type"] == "http.response.start":
                await send({"type": "http.response.body", "body": b""})
                raise _HeadAnswered()

        try:
            await self.app(scope, receive, amended_send)
        except BaseException as error:
            if not _only_head_answered(error):  # a streaming response raises it inside a task group
                raise


def _only_head_answered(error: BaseException) -> bool:
    if isinstance(error, BaseExceptionGroup):
        return all(_only_head_answered(inner) for inner in error.exceptions)
    return isinstance(error, _HeadAnswered)
