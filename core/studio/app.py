"""The studio's web app (Starlette): the page, its static files and the JSON API.

Security (see docs/studio.md): the server listens on 127.0.0.1 only; every request must
name that address (``Host``, and ``Origin`` when the browser sends one: DNS rebinding and
other sites' pages are refused); the page itself and every ``/api/`` route need the random
token of the printed URL (``?token=`` for the page and downloads, the ``X-Studio-Token``
header for the API; changes are POSTs, which must carry the header, so another site cannot
forge them), compared with :func:`secrets.compare_digest`; the only user files it reads are
the ones named on the command line (:attr:`Session.files`), compared after resolving links.
Static files are the package's own (the page's code and three.js).

Routes (JSON unless said otherwise; arrays travel as base64 of little-endian float32):

    GET  /                       the page (needs ?token=)
    GET  /static/...             index.html's scripts, styles, vendored three.js
    GET  /api/session            inputs, methods that apply, their parameters, live status
    GET  /api/source?start&stop  performance points, binary float32 (frames, P, 3)
    POST /api/run                {method, params} -> result summary (cached by method + params)
    GET  /api/result/vertices    ?id&start&stop: result vertices, binary float32
    GET  /api/result/error       ?id&start&stop: distance to the truth in % of face height, binary
    GET  /api/rig/{key}          a blendshape result's rig: neutral and deltas, binary float32
    POST /api/edit               {id, kind, frame, window, ...} -> summary + changed frames
    POST /api/undo, /api/redo    {id} -> summary
    POST /api/export             {id, format: glb|csv|pc2} -> {path}
    GET  /api/files              the files named on the command line
    GET  /api/file?path=         one of them, as it is on disk
    GET  /api/live?after=N       the newest live frame (waits up to 1 s for one past N)

Errors are JSON ``{"error": type, "message": what was wrong and how to fix it}``: 400 for a
bad request, 401 / 403 for the token, address and file checks, 404 for an unknown route
or id, 409 for what these inputs or this method cannot do, 422 when a method failed on
the inputs, 500 for a method's unexpected failure (the studio keeps running).
"""

from __future__ import annotations

import base64
import json
import os
import secrets
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any
from urllib.parse import parse_qs

import numpy as np
import numpy.typing as npt

from ..errors import (
    CapabilityError,
    FaceRetargetError,
    NotFittedError,
    NumericalError,
    OutputError,
    PluginError,
    UnknownNameError,
)
from .session import Result, Session

if TYPE_CHECKING:
    from starlette.responses import JSONResponse
    from starlette.types import ASGIApp, Receive, Scope, Send

    from ..model import Animation, Source

STATIC = Path(__file__).parent / "static"
TOKEN_HEADER = "x-studio-token"
#: Largest binary answer (bytes): bigger frame ranges are refused (the page asks in pieces).
MAX_BINARY = 64 * 2**20


class Guard:
    """ASGI middleware: the address, origin and token checks in front of every request."""

    def __init__(self, app: ASGIApp, *, token: str, port: int) -> None:
        self.app, self.token, self.port = app, token, port
        self.hosts = {f"127.0.0.1:{port}", f"localhost:{port}"}
        self.origins = {f"http://{h}" for h in self.hosts}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "lifespan":
            return await self.app(scope, receive, send)
        if scope["type"] != "http":  # no websockets
            return await _refuse(scope, send, 403, "only HTTP requests are served")
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        host = headers.get("host", "")
        if host not in self.hosts:
            return await _refuse(
                scope,
                send,
                403,
                f"Host {host!r} refused: the studio answers only at http://127.0.0.1:{self.port} "
                "(open the URL it printed)",
            )
        origin = headers.get("origin")
        if origin is not None and origin not in self.origins:
            return await _refuse(
                scope,
                send,
                403,
                f"Origin {origin!r} refused: only pages of http://127.0.0.1:{self.port} may call the studio",
            )
        path = scope.get("path", "")
        if path.startswith("/static/"):  # the package's own files: nothing of the user's
            return await self.app(scope, receive, send)
        query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
        given = headers.get(TOKEN_HEADER)
        if scope.get("method", "GET") not in ("GET", "HEAD"):
            where = "the X-Studio-Token header (changes need it; the page sends it)"
        else:
            given = given or (query.get("token") or [None])[0]
            where = "?token= or the X-Studio-Token header"
        if not given or not secrets.compare_digest(given.encode(), self.token.encode()):
            return await _refuse(
                scope,
                send,
                401,
                f"{'wrong' if given else 'missing'} token in {where}: open the URL "
                "`faceretarget studio` printed, which ends with ?token=...",
            )
        return await self.app(scope, receive, send)


async def _refuse(scope: Scope, send: Send, status: int, message: str) -> None:
    body = json.dumps(
        {"error": "forbidden" if status == 403 else "unauthorized", "message": message}
    )
    if scope["type"] == "websocket":
        await send({"type": "websocket.close", "code": 1008})
        return
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [(b"content-type", b"application/json"), (b"cache-control", b"no-store")],
        }
    )
    await send({"type": "http.response.body", "body": body.encode()})


def b64(array: npt.ArrayLike) -> str:
    """Little-endian float32 bytes of ``array``, base64 (the page's Float32Array)."""
    return base64.b64encode(np.ascontiguousarray(array, dtype="<f4").tobytes()).decode("ascii")


def summary(
    session: Session,
    result: Result,
    *,
    cached: bool = False,
    changed: Sequence[int] | None = None,
) -> dict[str, Any]:
    """What the page needs of a result: curves (base64 float32), head motion, the rig's key,
    the edits offered, the history and timings."""
    anim = result.animation
    entry = next(m for m in session.methods() if m["name"] == result.method)
    return {
        "id": result.id,
        "method": result.method,
        "params": result.params,
        "version": result.version,
        "cached": cached,
        "n_frames": anim.n_frames,
        "fps": anim.fps,
        "n_vertices": summary_vertices(anim),
        "outputs": "weights" if anim.is_blendshape_based else "vertices",
        "weight_names": list(anim.weight_names),
        "weights": None if anim.weights is None else b64(anim.weights),
        "head_motion": None if anim.head_motion is None else b64(anim.head_motion),
        "rig": session.rig_key(anim),
        "edit": entry["edit"],
        "edit_window": entry["edit_window"],
        "edits": list(result.edits[: result.position]),
        "undo": result.undo_steps,
        "redo": result.redo_steps,
        "seconds": result.seconds,
        "changed": changed,
    }


def create_app(session: Session, *, token: str, port: int) -> Guard:
    """The ASGI app for ``session``, answering only at ``127.0.0.1:port`` with ``token``."""
    from starlette.applications import Starlette
    from starlette.concurrency import run_in_threadpool
    from starlette.requests import Request
    from starlette.responses import FileResponse, JSONResponse, Response
    from starlette.routing import Mount, Route
    from starlette.staticfiles import StaticFiles

    def binary(array: npt.ArrayLike) -> Response:
        arr = np.ascontiguousarray(array, dtype="<f4")
        return Response(
            arr.tobytes(),
            media_type="application/octet-stream",
            headers={"x-shape": ",".join(map(str, arr.shape)), "cache-control": "no-store"},
        )

    async def body(request: Request) -> dict:
        raw = await request.body()
        try:
            data = json.loads(raw or b"{}")
        except ValueError as exc:
            raise _BadRequest(
                f"the request body is not JSON ({exc}); send an object such as "
                '{"method": "NAME", "params": {}}'
            ) from None
        if not isinstance(data, dict):
            raise _BadRequest(f"the request body must be a JSON object, got {type(data).__name__}")
        return data

    def frame_range(request: Request, n_frames: int, per_frame: int) -> tuple[int, int]:
        try:
            start = int(request.query_params.get("start", 0))
            stop = int(request.query_params.get("stop", n_frames))
        except ValueError:
            raise _BadRequest("start and stop must be whole frame numbers") from None
        if not 0 <= start < stop <= n_frames:
            raise _BadRequest(f"frames [{start}, {stop}) are outside 0..{n_frames}")
        if (stop - start) * per_frame * 4 > MAX_BINARY:
            raise _BadRequest(
                f"{stop - start} frames are too many for one answer; ask for at most "
                f"{max(1, MAX_BINARY // (per_frame * 4))} at a time"
            )
        return start, stop

    async def index(request: Request) -> Response:
        page = (STATIC / "index.html").read_text(encoding="utf-8")
        return Response(
            page,
            media_type="text/html",
            headers={
                "cache-control": "no-store",
                "content-security-policy": "default-src 'self'; img-src 'self' data: blob:; "
                "connect-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'",
                "referrer-policy": "no-referrer",
            },
        )

    async def session_info(request: Request) -> Response:
        src, tgt = session.source, session.target
        methods = await run_in_threadpool(session.methods)
        applicable = [m for m in methods if m["applies"]]
        # first: a method that edits weight curves (fast, and the curves show it), then any editor
        editors = [m for m in applicable if "weights" in m["edit"]] + [
            m for m in applicable if m["edit"]
        ]
        default = editors[0]["name"] if editors else None
        default = session_defaults.get("method") or default or (applicable or [{}])[0].get("name")
        info: dict[str, Any] = {
            "name": session.name,
            "source": {
                "kind": src.kind,
                "n_frames": src.n_frames,
                "fps": src.fps,
                "n_points": session.source_frames(0, 1).shape[1],
                "triangles": _triangles(src),
            },
            "target": {
                "n_vertices": tgt.neutral.n_vertices,
                "neutral": b64(tgt.neutral.vertices),
                "triangles": base64.b64encode(
                    np.ascontiguousarray(tgt.neutral.triangles, dtype="<u4").tobytes()
                ).decode(),
                "height": session.face_height,
            },
            "truth": session.truth is not None,
            "methods": methods,
            "default_method": default,
            "default_params": session_defaults.get("params", {}),
            "out_dir": str(session.out_dir.resolve()),
            "files": _files(session),
            "live": None if session.live is None else session.live.info(),
        }
        return JSONResponse(info)

    async def source_points(request: Request) -> Response:
        n = session.source.n_frames
        probe = await run_in_threadpool(session.source_frames, 0, 1)
        start, stop = frame_range(request, n, probe.shape[1] * 3)
        return binary(await run_in_threadpool(session.source_frames, start, stop))

    async def run(request: Request) -> Response:
        data = await body(request)
        result, cached = await run_in_threadpool(
            session.run, data.get("method"), data.get("params")
        )
        return JSONResponse(summary(session, result, cached=cached))

    async def result_vertices(request: Request) -> Response:
        result = session.result(request.query_params.get("id"))
        anim = result.animation
        n_vertices = summary_vertices(anim)
        start, stop = frame_range(request, anim.n_frames, n_vertices * 3)
        return binary(await run_in_threadpool(session.frames, anim, start, stop))

    async def result_error(request: Request) -> Response:
        result = session.result(request.query_params.get("id"))
        anim = result.animation
        start, stop = frame_range(request, anim.n_frames, summary_vertices(anim))
        return binary(await run_in_threadpool(session.error_frames, anim, start, stop))

    async def rig(request: Request) -> Response:
        rig = session.rig(request.path_params["key"])
        stacked = np.concatenate([rig.neutral.vertices[None], rig.deltas], axis=0)
        return binary(stacked)

    async def edit(request: Request) -> Response:
        data = await body(request)
        result, changed = await run_in_threadpool(session.edit, data.get("id"), data)
        return JSONResponse(summary(session, result, changed=changed))

    async def undo(request: Request) -> Response:
        data = await body(request)
        result = await run_in_threadpool(session.undo, data.get("id"))
        return JSONResponse(summary(session, result, changed=[0, result.animation.n_frames - 1]))

    async def redo(request: Request) -> Response:
        data = await body(request)
        result = await run_in_threadpool(session.redo, data.get("id"))
        return JSONResponse(summary(session, result, changed=[0, result.animation.n_frames - 1]))

    async def export(request: Request) -> Response:
        data = await body(request)
        path = await run_in_threadpool(session.export, data.get("id"), data.get("format"))
        return JSONResponse({"path": str(Path(path).resolve()), "bytes": Path(path).stat().st_size})

    async def files(request: Request) -> Response:
        return JSONResponse({"files": _files(session)})

    async def file(request: Request) -> Response:
        asked = request.query_params.get("path", "")
        allowed = {os.path.realpath(f): f for f in session.files if Path(f).is_file()}
        real = os.path.realpath(asked) if asked else ""
        if real not in allowed:
            return _error(
                403,
                "forbidden",
                f"{asked!r} is not one of the files named on the command line; the studio reads only "
                f"those: {', '.join(str(f) for f in allowed.values()) or '(none)'}",
            )
        return FileResponse(real, filename=Path(real).name, headers={"cache-control": "no-store"})

    async def live(request: Request) -> Response:
        link = session.live
        if link is None:
            raise CapabilityError("studio: no live stream; start with --live PORT")
        try:
            after = int(request.query_params.get("after", 0))
        except ValueError:
            raise _BadRequest("after must be a whole frame number") from None
        frame = await run_in_threadpool(link.latest, after, 1.0)
        out = {"info": link.info(), "frame": None}
        if frame is not None:
            out["frame"] = {
                "seq": frame["seq"],
                "source": b64(frame["source"]),
                "target": b64(frame["target"]),
                "latency_ms": frame["latency_ms"],
            }
        return JSONResponse(out)

    async def not_found(request: Request, exc: Exception) -> Response:
        return _error(
            404, "not_found", f"no route {request.url.path!r}; the API is listed in docs/studio.md"
        )

    async def method_not_allowed(request: Request, exc: Exception) -> Response:
        return _error(
            405, "method_not_allowed", f"{request.method} is not accepted at {request.url.path}"
        )

    async def failed(request: Request, exc: Exception) -> Response:
        return _error_for(exc)

    session_defaults = session.defaults
    routes = [
        Route("/", index),
        Route("/api/session", session_info),
        Route("/api/source", source_points),
        Route("/api/run", run, methods=["POST"]),
        Route("/api/result/vertices", result_vertices),
        Route("/api/result/error", result_error),
        Route("/api/rig/{key}", rig),
        Route("/api/edit", edit, methods=["POST"]),
        Route("/api/undo", undo, methods=["POST"]),
        Route("/api/redo", redo, methods=["POST"]),
        Route("/api/export", export, methods=["POST"]),
        Route("/api/files", files),
        Route("/api/file", file),
        Route("/api/live", live),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    app = Starlette(
        routes=routes,
        # FaceRetargetError: answered and done; any other exception: answered, then logged
        # with its traceback by the server (Starlette's ServerErrorMiddleware re-raises it)
        exception_handlers={
            404: not_found,
            405: method_not_allowed,
            FaceRetargetError: failed,
            Exception: failed,
        },
    )
    return Guard(app, token=token, port=port)


class _BadRequest(FaceRetargetError, ValueError):
    """A request the API cannot read (answered 400; never leaves the app)."""


def summary_vertices(anim: Animation) -> int:
    rig = anim.rig if anim.is_blendshape_based else None
    return int(rig.neutral.n_vertices if rig is not None else anim.vertices.shape[1])


def _triangles(source: Source) -> str | None:
    perf = source.performance
    tri = getattr(perf, "triangles", None)
    if tri is None and source.kind == "weights" and source.rig is not None:
        tri = source.rig.neutral.triangles
    if tri is None:
        return None
    return base64.b64encode(np.ascontiguousarray(tri, dtype="<u4").tobytes()).decode()


def _files(session: Session) -> list[dict[str, Any]]:
    return [
        {"path": str(f), "name": Path(f).name, "bytes": Path(f).stat().st_size}
        for f in session.files
        if Path(f).is_file()
    ]


def _error(status: int, kind: str, message: str) -> JSONResponse:
    from starlette.responses import JSONResponse

    return JSONResponse({"error": kind, "message": message}, status_code=status)


def _error_for(exc: Exception) -> JSONResponse:
    """The JSON answer for an exception raised while serving a request."""
    text = " ".join((str(exc).strip() or type(exc).__name__).split())
    if isinstance(exc, _BadRequest):
        return _error(400, "bad_request", text)
    if isinstance(exc, UnknownNameError):
        return _error(
            404 if "no result" in text or "no rig" in text else 400, type(exc).__name__, text
        )
    if isinstance(exc, CapabilityError):
        return _error(409, type(exc).__name__, text)
    if isinstance(exc, (NumericalError, PluginError, NotFittedError)):
        return _error(422, type(exc).__name__, text)
    if isinstance(exc, OutputError):
        return _error(409, type(exc).__name__, text)
    if isinstance(exc, FaceRetargetError):
        return _error(400, type(exc).__name__, text)
    return _error(
        500,
        "internal",
        f"{type(exc).__name__}: {text} (an unexpected failure; the studio keeps running, "
        "see its terminal for the traceback)",
    )
