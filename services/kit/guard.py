"""What every service's REST API checks before a route runs, and how it answers bad input.

:class:`RequestGuard` is a pure ASGI middleware (it sees the raw request, before FastAPI
parses anything):

- **Host**: the Host header must name an allowed host (``AOI3D_ALLOWED_HOSTS``), else 400 —
  a web page that rebinds its own DNS name to 127.0.0.1 reaches nothing.
- Requests that change state (every method but GET, HEAD, OPTIONS):
  - an ``Origin`` header, when a browser sends one, must name an allowed host, else 403 —
    a page of another site cannot drive the pipeline;
  - with a control token configured, ``Authorization: Bearer <token>`` (constant-time
    compare), else 401;
  - a body of at most ``max_body_bytes`` (413; checked on Content-Length and while reading,
    so chunked bodies are bounded too), of content type JSON (415: a cross-site HTML form
    cannot send one), with no NaN or Infinity in it (422: they are not JSON, and Python's
    parser would otherwise let them through).

:func:`install_error_handlers` makes validation errors (422) and HTTP errors answer with a
short message that never echoes more than an excerpt of the input (FastAPI's default 422
echoes the whole body back and fails with 500 on NaN).

Starlette's ``TrustedHostMiddleware`` checks Host alone; the Origin, token, body and NaN
checks belong together on the same buffered body, hence one small middleware here.
"""

from __future__ import annotations

import hmac
import json
import logging
import math
from collections.abc import Awaitable, Callable, MutableMapping
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger(__name__)

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
EXCERPT_CHARS = 200
"""Longest piece of a client's input an error message quotes."""


def excerpt(text: str, limit: int = EXCERPT_CHARS) -> str:
    return text if len(text) <= limit else text[:limit] + f"… ({len(text)} characters)"


def host_name(value: str) -> str:
    """``127.0.0.1:8103`` → ``127.0.0.1``; ``[::1]:8103`` → ``::1``; lower case."""
    value = value.strip().lower()
    if value.startswith("["):
        return value[1:value.find("]")] if "]" in value else value
    if value.count(":") == 1:
        return value.split(":", 1)[0]
    return value


class _NotJSONNumber(ValueError):
    pass


def _reject_constant(name: str) -> float:
    raise _NotJSONNumber(f"{name} is not a valid JSON number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise _NotJSONNumber(f"{excerpt(text, 40)} is out of the range of a finite number")
    return value


def non_finite_problem(body: bytes) -> str | None:
    """Why ``body`` carries a number that is not finite (NaN, Infinity, 1e999), or None."""
    try:
        json.loads(body, parse_constant=_reject_constant, parse_float=_finite_float)
    except _NotJSONNumber as err:
        return str(err)
    except ValueError:
        return None  # not JSON at all: FastAPI's own parser says so (422)
    return None


class RequestGuard:
    def __init__(self, app: Callable, *, allowed_hosts: list[str], token: str | None,
                 max_body_bytes: int) -> None:
        self.app = app
        self.any_host = "*" in allowed_hosts
        self.allowed = frozenset(h.lower() for h in allowed_hosts)
        self.token = token
        self.max_body = int(max_body_bytes)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1")
                   for k, v in scope.get("headers", [])}
        host = headers.get("host", "")
        if not self._allowed(host_name(host)):
            await _answer(send, 400, f"host {excerpt(host, 80)!r} is not allowed; "
                                     f"AOI3D_ALLOWED_HOSTS lists the accepted names")
            return
        if scope["method"] in SAFE_METHODS:
            await self.app(scope, receive, send)
            return
        origin = headers.get("origin")
        if origin is not None:
            origin_host = urlsplit(origin).hostname if origin != "null" else None
            if origin_host is None or not self._allowed(origin_host):
                await _answer(send, 403, f"requests from origin {excerpt(origin, 80)!r} may "
                                         f"not change state (AOI3D_ALLOWED_HOSTS)")
                return
        if self.token is not None:
            given = headers.get("authorization", "")
            if not hmac.compare_digest(given.encode(), f"Bearer {self.token}".encode()):
                await _answer(send, 401, "this endpoint needs the control token: "
                                         "Authorization: Bearer <AOI3D_CONTROL_TOKEN>",
                              extra=[(b"www-authenticate", b"Bearer")])
                return
        length = headers.get("content-length")
        if length is not None and (not length.isdigit() or int(length) > self.max_body):
            await _answer(send, 413, f"request body over {self.max_body} bytes")
            return
        body, more = b"", True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            body += message.get("body", b"")
            more = message.get("more_body", False)
            if len(body) > self.max_body:
                await _answer(send, 413, f"request body over {self.max_body} bytes")
                return
        if body:
            ctype = headers.get("content-type", "").split(";", 1)[0].strip().lower()
            if ctype != "application/json" and not ctype.endswith("+json"):
                await _answer(send, 415, f"request bodies must be JSON (Content-Type: "
                                         f"application/json), got {excerpt(ctype, 60)!r}")
                return
            problem = non_finite_problem(body)
            if problem is not None:
                await _answer(send, 422, problem)
                return
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    def _allowed(self, host: str) -> bool:
        return self.any_host or host in self.allowed


async def _answer(send: Send, status: int, detail: str,
                  extra: list[tuple[bytes, bytes]] | None = None) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"),
                            (b"content-length", str(len(body)).encode()), *(extra or [])]})
    await send({"type": "http.response.body", "body": body})


def _clean_error(err: dict[str, Any]) -> dict[str, Any]:
    """One pydantic error without the input it was given (never echoed) or its context."""
    return {"loc": list(err.get("loc", ())), "msg": excerpt(str(err.get("msg", ""))),
            "type": err.get("type", "")}


def install_error_handlers(app: FastAPI) -> None:
    @app.exception_handler(RequestValidationError)
    async def _validation(_request: Request, exc: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": [_clean_error(e) for e in exc.errors()[:20]]},
                            status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _http(_request: Request, exc: StarletteHTTPException) -> JSONResponse:
        detail = exc.detail
        if isinstance(detail, str):
            detail = excerpt(detail, 1000)
        return JSONResponse({"detail": detail}, status_code=exc.status_code,
                            headers=getattr(exc, "headers", None))


def guard_app(app: FastAPI, *, allowed_hosts: list[str], token: str | None,
              max_body_bytes: int) -> None:
    """Install :class:`RequestGuard` and the error handlers on ``app``."""
    install_error_handlers(app)
    app.add_middleware(RequestGuard, allowed_hosts=allowed_hosts, token=token,
                       max_body_bytes=max_body_bytes)


class OutsideRoots(ValueError):
    """A file path from a request that does not lie in the configured folders."""


def confined_path(text: str, roots: list[str], what: str) -> Path:
    """``text`` as a path (relative ones from the working directory, symlinks resolved) that
    lies in one of ``roots`` (``AOI3D_FILES_ROOTS``); else :class:`OutsideRoots`, whose
    message never says whether the path exists. A path that cannot even be resolved (``~x``
    of no such user, a NUL byte, a symlink loop, too long a name) is outside too."""
    try:
        path = Path(text).expanduser().resolve()
    except (RuntimeError, ValueError, OSError):
        raise OutsideRoots(f"{what} must lie in {' or '.join(f'{r}/' for r in roots)} "
                           f"(AOI3D_FILES_ROOTS)") from None
    for root in roots:
        if path.is_relative_to(Path(root).expanduser().resolve()):
            return path
    raise OutsideRoots(f"{what} must lie in {' or '.join(f'{r}/' for r in roots)} "
                       f"(AOI3D_FILES_ROOTS)")


def files_in_roots(roots: list[str], pattern: str, limit: int = 500) -> list[str]:
    """Files matching ``pattern`` under ``roots``, as paths relative to the working directory
    where they can be (sorted, at most ``limit``)."""
    cwd = Path.cwd().resolve()
    found: set[str] = set()
    for root in roots:
        base = Path(root).expanduser()
        if not base.is_dir():
            continue
        for path in base.rglob(pattern):
            resolved = path.resolve()
            if not path.is_file() or not resolved.is_relative_to(base.resolve()):
                continue
            found.add(str(resolved.relative_to(cwd)) if resolved.is_relative_to(cwd)
                      else str(resolved))
    return sorted(found)[:limit]
