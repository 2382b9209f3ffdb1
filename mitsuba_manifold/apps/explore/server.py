"""The explorer's web app (Starlette): the page, a JSON/binary API and a websocket for drags.

Drags go over one websocket per tab: the page sends the latest latent point whenever the
pointer moves, the server keeps only the newest request of each kind that arrived while it
was busy (stale points are dropped, not queued) and answers with binary messages
``[uint32 n][n bytes of JSON meta][payload]``. Everything else is plain HTTP
(:func:`create_app` lists the routes). Errors in a request answer 400 with
``{"error": message}``; no traceback reaches the page.
"""

import asyncio
import json
import os
import re
import struct
from urllib.parse import urlsplit

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles
from starlette.websockets import WebSocketDisconnect

from ...errors import InputError, UnknownMaterialError
from . import encode

STATIC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "static")
#: What answers 400: bad input (a bad value, an unknown name).
BAD_REQUEST = (InputError, UnknownMaterialError)
_JOB_ID = re.compile(r"^r[0-9]{1,9}$")
#: Websocket requests, answered in this order when several wait.
KINDS = ("frame", "material", "table")
#: How a websocket whose tab went away fails (uvicorn's ClientDisconnected is an OSError).
GONE = (WebSocketDisconnect, OSError)


def pack(meta, payload=b""):
    """One binary websocket message: JSON meta then payload."""
    head = json.dumps(meta).encode()
    return struct.pack("<I", len(head)) + head + payload


def same_origin(conn):
    """False when a browser sends a request from a page of another site (its Origin header
    names another host): such pages may not drive the explorer's websocket or start renders."""
    origin = conn.headers.get("origin")
    return origin is None or urlsplit(origin).netloc == conn.headers.get("host")


def _query(request, key, default=None):
    return request.query_params.get(key, default)


def create_app(explorer):
    """The Starlette app serving ``explorer`` (a :class:`~.service.Explorer`).

    Routes: ``/`` the page; ``/static/*`` its files; ``/api/info``; ``/api/frame?basis&x&exposure&format``
    (the image); ``/api/material?x``; ``/api/table?x`` (float16 preview table, layout in the
    ``X-Table`` header); ``/api/map?dims&x``; ``/api/snippet?x``; ``/api/path?basis&a&b&steps``;
    ``POST /api/reference`` ``{basis, x, spp}``, ``/api/reference/{id}``,
    ``/api/reference/{id}/{blend|reference|error}.png``; websocket ``/ws``.
    """
    ex = explorer

    def x_of(request):
        return ex.point(_query(request, "x", ""), "x")

    async def index(request):
        return FileResponse(os.path.join(STATIC, "index.html"), headers={"Cache-Control": "no-cache"})

    async def info(request):
        return JSONResponse(ex.info())

    async def frame(request):
        x = x_of(request)
        exposure = ex.number(_query(request, "exposure"), "exposure", -20, 20, 0.0)
        fmt = _query(request, "format", "png")
        data, meta = await run_in_threadpool(ex.frame, _query(request, "basis"), x, exposure, fmt)
        return Response(data, media_type=encode.MIME[fmt], headers={"X-Frame": json.dumps(meta)})

    async def material_route(request):
        x = x_of(request)
        return JSONResponse(await run_in_threadpool(ex.material, x))

    async def table(request):
        x = x_of(request)
        data, meta = await run_in_threadpool(ex.preview_table, x)
        return Response(data, media_type="application/octet-stream", headers={"X-Table": json.dumps(meta)})

    async def latent_map(request):
        dims = _query(request, "dims", "0,1")
        center = x_of(request) if _query(request, "x") else ex.manifold.latent.mean(axis=0)
        m = await run_in_threadpool(ex.latent_map, dims, center, _query(request, "extent"))
        import base64
        png = await run_in_threadpool(encode.png_bytes, m.image)
        return JSONResponse(dict(m.info(), png="data:image/png;base64," + base64.b64encode(png).decode()))

    async def snippet(request):
        return JSONResponse(ex.snippets(x_of(request)))

    async def path(request):
        cmd = ex.path_command(_query(request, "basis"), _query(request, "a", ""), _query(request, "b", ""),
                              _query(request, "steps"))
        return JSONResponse({"command": cmd})

    async def reference_start(request):
        if not same_origin(request):
            return JSONResponse({"error": "cross-origin request refused"}, status_code=403)
        try:
            body = await request.json()
        except ValueError:
            raise InputError("the request body must be JSON like {\"x\": [0.1, 0.2], \"spp\": 256}") from None
        if not isinstance(body, dict):
            raise InputError("the request body must be a JSON object")
        x = ex.point(body.get("x"), "x")
        job = await run_in_threadpool(ex.start_reference, body.get("basis"), x, body.get("spp"))
        return JSONResponse(job.status())

    def job_of(request):
        job_id = request.path_params["job"]
        job = ex.references.get(job_id) if _JOB_ID.match(job_id) else None
        if job is None:
            raise InputError(f"unknown reference job {job_id!r}")
        return job

    async def reference_status(request):
        return JSONResponse(job_of(request).status())

    async def reference_image(request):
        job = job_of(request)
        exposure = ex.number(_query(request, "exposure"), "exposure", -20, 20, 0.0)
        png = await run_in_threadpool(ex.reference_image, job.id, request.path_params["which"], exposure)
        return Response(png, media_type="image/png")

    async def websocket(ws):
        if not same_origin(ws):
            await ws.close(code=1008)   # policy violation: a page of another site
            return
        await ws.accept()
        pending, errors, wake = {}, [], asyncio.Event()   # only the worker sends

        async def reader():
            while True:
                text = await ws.receive_text()
                try:
                    req = json.loads(text)
                    kind = req["type"]
                except (ValueError, KeyError, TypeError):
                    errors.append({"type": "error", "error": f"bad message {text[:80]!r}: expected JSON with a 'type'"})
                else:
                    if kind in KINDS:
                        pending[kind] = req   # replaces an older request of the same kind not yet answered
                    else:
                        errors.append({"type": "error", "seq": req.get("seq"),
                                       "error": f"unknown message type {kind!r}; expected one of {KINDS}"})
                wake.set()

        async def worker():
            while True:
                await wake.wait()
                wake.clear()
                while errors or pending:
                    if errors:
                        await ws.send_bytes(pack(errors.pop(0)))
                        continue
                    kind = next(k for k in KINDS if k in pending)
                    await ws.send_bytes(await _answer(kind, pending.pop(kind)))

        async def _answer(kind, req):
            seq = req.get("seq")
            try:
                x = ex.point(req.get("x"), "x")
                if kind == "frame":
                    exposure = ex.number(req.get("exposure"), "exposure", -20, 20, 0.0)
                    data, meta = await run_in_threadpool(ex.frame, req.get("basis"), x, exposure,
                                                         req.get("format", "jpeg"))
                elif kind == "material":
                    data, meta = b"", await run_in_threadpool(ex.material, x)
                else:
                    data, meta = await run_in_threadpool(ex.preview_table, x)
            except BAD_REQUEST as e:
                return pack({"type": "error", "kind": kind, "seq": seq, "error": str(e)})
            return pack(dict(meta, type=kind, seq=seq, x=[float(v) for v in x]), data)

        read, work = asyncio.ensure_future(reader()), asyncio.ensure_future(worker())
        try:
            await asyncio.wait([read, work], return_when=asyncio.FIRST_EXCEPTION)
        finally:
            read.cancel()
            work.cancel()
        for t in (work, read):   # a tab going away (also while an answer is sent) is no error
            if t.done() and not t.cancelled() and not isinstance(t.exception(), (type(None),) + GONE):
                raise t.exception()

    async def bad_request(request, exc):
        return JSONResponse({"error": str(exc)}, status_code=400)

    async def http_error(request, exc):
        return JSONResponse({"error": exc.detail}, status_code=exc.status_code)

    async def server_error(request, exc):
        return JSONResponse({"error": f"internal error ({type(exc).__name__}); see the server's console"},
                            status_code=500)

    routes = [
        Route("/", index),
        Route("/api/info", info),
        Route("/api/frame", frame),
        Route("/api/material", material_route),
        Route("/api/table", table),
        Route("/api/map", latent_map),
        Route("/api/snippet", snippet),
        Route("/api/path", path),
        Route("/api/reference", reference_start, methods=["POST"]),
        Route("/api/reference/{job}", reference_status),
        Route("/api/reference/{job}/{which}.png", reference_image),
        WebSocketRoute("/ws", websocket),
        Mount("/static", StaticFiles(directory=STATIC), name="static"),
    ]
    handlers = {e: bad_request for e in BAD_REQUEST}
    handlers[HTTPException] = http_error
    handlers[Exception] = server_error
    app = Starlette(routes=routes, exception_handlers=handlers)
    app.state.explorer = ex
    return app
