"""The explorer's web app (Starlette): the page, a JSON/binary API and a websocket for drags.

Drags go over one websocket per tab (:mod:`.session`: requests tagged with their point, the
newest of each kind answered). Everything else is plain HTTP (:func:`create_app` lists the
routes). Every request passes :class:`~.guard.Guard` first: the Host/Origin allow-list
(DNS rebinding, other sites) and the body size limit. Errors in a request answer 400 with
``{"error": message}`` (one line); no traceback reaches the page.
"""

from __future__ import annotations

import base64
import json
import os
import re
from typing import TYPE_CHECKING

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException
from starlette.middleware import Middleware
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles

from ....errors import BusyError, InputError
from .. import encode
from ..acquire import MAX_UPLOAD
from ..service import show
from .guard import MAX_BODY, Guard
from .session import BAD_REQUEST, Session

if TYPE_CHECKING:
    from typing import Any

    import numpy as np


STATIC = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "static")
_JOB_ID = re.compile(r"^r[0-9]{1,9}$")
_ACQ_ID = re.compile(r"^a[0-9]{1,9}$")


async def _json_object(request, example: str) -> dict:
    """The request's body as a JSON object (the body was read by Guard, within its size limit);
    ``example`` shows a valid body in the error.
    """
    try:
        body = json.loads(await request.body())
    except (ValueError, RecursionError):
        raise InputError(f"the request body must be JSON like {example}") from None
    if not isinstance(body, dict):
        raise InputError("the request body must be a JSON object")
    return body


def _job(request, jobs, pattern: re.Pattern, what: str) -> Any:
    """The job of ``jobs`` the request's path names (an id matching ``pattern``)."""
    job_id = request.path_params["job"]
    job = jobs.get(job_id) if pattern.match(job_id) else None
    if job is None:
        raise InputError(f"unknown {what} {show(job_id)}")
    return job


def _query(request, key, default=None):
    return request.query_params.get(key, default)


class Api:
    """The HTTP endpoints of one :class:`~.service.Explorer` (each method one route of
    :func:`create_app`); the work is in the explorer, run off the event loop.
    """

    def __init__(self, explorer) -> None:
        self.ex = explorer

    def x_of(self, request) -> np.ndarray:
        return self.ex.point(_query(request, "x", ""), "x")

    def exposure_of(self, request) -> float:
        return self.ex.number(_query(request, "exposure"), "exposure", -20, 20, 0.0)

    async def index(self, request) -> FileResponse:
        return FileResponse(
            os.path.join(STATIC, "index.html"), headers={"Cache-Control": "no-cache"}
        )

    async def info(self, request) -> JSONResponse:
        return JSONResponse(self.ex.info())

    async def frame(self, request) -> Response:
        x, exposure, fmt = (
            self.x_of(request),
            self.exposure_of(request),
            _query(request, "format", "png"),
        )
        data, meta = await run_in_threadpool(
            self.ex.frame, _query(request, "basis"), x, exposure, fmt
        )
        return Response(data, media_type=encode.MIME[fmt], headers={"X-Frame": json.dumps(meta)})

    async def material(self, request) -> JSONResponse:
        return JSONResponse(await run_in_threadpool(self.ex.material, self.x_of(request)))

    async def table(self, request) -> Response:
        data, meta = await run_in_threadpool(self.ex.preview_table, self.x_of(request))
        return Response(
            data, media_type="application/octet-stream", headers={"X-Table": json.dumps(meta)}
        )

    async def latent_map(self, request) -> JSONResponse:
        dims = _query(request, "dims", "0,1")
        center = (
            self.x_of(request) if _query(request, "x") else self.ex.manifold.latent.mean(axis=0)
        )
        png, meta = await run_in_threadpool(
            self.ex.map_png, dims, center, _query(request, "extent")
        )
        return JSONResponse(
            dict(meta, png="data:image/png;base64," + base64.b64encode(png).decode())
        )

    async def environment(self, request) -> Response:
        data, meta = await run_in_threadpool(self.ex.environment, _query(request, "basis"))
        return Response(
            data, media_type="application/octet-stream", headers={"X-Env": json.dumps(meta)}
        )

    async def snippet(self, request) -> JSONResponse:
        return JSONResponse(self.ex.snippets(self.x_of(request), _query(request, "folder")))

    async def path(self, request) -> JSONResponse:
        cmd = self.ex.path_command(
            _query(request, "basis"),
            _query(request, "a", ""),
            _query(request, "b", ""),
            _query(request, "steps"),
            _query(request, "kind"),
        )
        return JSONResponse({"command": cmd})

    async def route(self, request) -> JSONResponse:
        """The path's points when computed, else ``{"state": "computing"}`` (ask again)."""
        future = await run_in_threadpool(
            self.ex.route,
            _query(request, "a", ""),
            _query(request, "b", ""),
            _query(request, "steps"),
            _query(request, "kind"),
        )
        if not future.done():  # this request stays a waiter: the path is computed for the next poll
            return JSONResponse({"state": "computing"})
        self.ex.walks.release(future)
        return JSONResponse(
            dict(future.result(), state="ready")
        )  # a failed path raises its InputError

    async def thumbs(self, request) -> Response:
        if self.ex.thumbs is None:
            raise InputError("this explorer renders no thumbnails (--no-thumbnails)")
        return Response(
            self.ex.thumbs.sheet(),
            media_type="image/png",
            headers={"Cache-Control": "max-age=3600"},
        )

    async def reference_start(self, request) -> JSONResponse:
        body = await _json_object(request, '{"x": [0.1, 0.2], "spp": 256}')
        x = self.ex.point(body.get("x"), "x")
        kind = body.get("kind", "reference")
        if kind not in ("reference", "refine"):
            raise InputError(f"kind must be 'reference' or 'refine', got {show(kind)}")
        start = self.ex.start_refine if kind == "refine" else self.ex.start_reference
        job = await run_in_threadpool(start, body.get("basis"), x, body.get("spp"), body.get("tab"))
        return JSONResponse(job.status())

    async def reference_cancel(self, request) -> JSONResponse:
        """Cancel a job (queued: never starts; rendering: stops after its pass)."""
        job = self.ex.references.cancel(self.job_of(request).id)
        return JSONResponse(job.status())

    def job_of(self, request) -> Any:
        return _job(request, self.ex.references, _JOB_ID, "reference job")

    async def reference_status(self, request) -> JSONResponse:
        return JSONResponse(self.job_of(request).status())

    async def reference_image(self, request) -> Response:
        job, exposure = self.job_of(request), self.exposure_of(request)
        png = await run_in_threadpool(
            self.ex.reference_image, job.id, request.path_params["which"], exposure
        )
        return Response(png, media_type="image/png")

    async def acquire_start(self, request) -> JSONResponse:
        """Start an acquisition: a JSON body ``{basis, photo, mask}`` (files as data: URLs)."""
        body = await _json_object(
            request, '{"basis": "name", "photo": "data:image/png;base64,..."}'
        )  # at most MAX_UPLOAD bytes
        job = await run_in_threadpool(
            self.ex.start_acquire, body.get("basis"), body.get("photo"), body.get("mask")
        )
        return JSONResponse(job.status())

    def acquisition_of(self, request) -> Any:
        return _job(request, self.ex.acquisitions, _ACQ_ID, "acquisition")

    async def acquire_status(self, request) -> JSONResponse:
        return JSONResponse(self.acquisition_of(request).status())

    async def acquire_image(self, request) -> Response:
        job, exposure = self.acquisition_of(request), self.exposure_of(request)
        png = await run_in_threadpool(
            self.ex.acquisitions.image, job.id, request.path_params["which"], exposure
        )
        return Response(png, media_type="image/png")

    async def websocket(self, ws) -> None:
        await Session(ws, self.ex).run()  # the handshake passed Guard's allow-list

    def routes(self) -> list:
        return [
            Route("/", self.index),
            Route("/api/info", self.info),
            Route("/api/frame", self.frame),
            Route("/api/material", self.material),
            Route("/api/table", self.table),
            Route("/api/map", self.latent_map),
            Route("/api/snippet", self.snippet),
            Route("/api/env", self.environment),
            Route("/api/path", self.path),
            Route("/api/route", self.route),
            Route("/api/thumbs.png", self.thumbs),
            Route("/api/reference", self.reference_start, methods=["POST"]),
            Route("/api/reference/{job}", self.reference_status),
            Route("/api/reference/{job}/cancel", self.reference_cancel, methods=["POST"]),
            Route("/api/reference/{job}/{which}.png", self.reference_image),
            Route("/api/acquire", self.acquire_start, methods=["POST"]),
            Route("/api/acquire/{job}", self.acquire_status),
            Route("/api/acquire/{job}/{which}.png", self.acquire_image),
            WebSocketRoute("/ws", self.websocket),
            Mount("/static", StaticFiles(directory=STATIC), name="static"),
        ]


async def _bad_request(request, exc) -> JSONResponse:
    return JSONResponse({"error": str(exc)}, status_code=400)


async def _busy(request, exc) -> JSONResponse:
    return JSONResponse({"error": str(exc)}, status_code=429)


async def _http_error(request, exc) -> JSONResponse:
    return JSONResponse({"error": exc.detail}, status_code=exc.status_code)


async def _server_error(request, exc) -> JSONResponse:
    return JSONResponse(
        {"error": f"internal error ({type(exc).__name__}); see the server's console"},
        status_code=500,
    )


def create_app(explorer, allow=None, max_body=MAX_BODY) -> Starlette:
    """The Starlette app serving ``explorer`` (a :class:`~.service.Explorer`).

    ``allow``: the :class:`~.guard.AllowList` of hosts and origins (default: ``127.0.0.1``,
    ``localhost`` and ``[::1]`` on any port); ``max_body``: largest request body in bytes.

    Routes (:meth:`Api.routes`): ``/`` the page; ``/static/*`` its files; ``/api/info``;
    ``/api/frame?basis&x&exposure&format`` (the image); ``/api/material?x``; ``/api/table?x``
    (float16 preview table, layout in the ``X-Table`` header); ``/api/map?dims&x``;
    ``/api/snippet?x&folder``; ``/api/env?basis`` (the scene's environment for the sphere);
    ``/api/path?basis&a&b&steps&kind`` (the blend.py command); ``/api/route?a&b&steps&kind`` (the
    path's points); ``/api/thumbs.png`` (the thumbnail sheet); ``POST /api/reference`` ``{basis, x,
    spp}``, ``/api/reference/{id}``, ``POST /api/reference/{id}/cancel``,
    ``/api/reference/{id}/{blend|reference|error}.png``; ``POST /api/acquire`` ``{basis, photo,
    mask}`` (a photo of the basis's scene, files as data: URLs, at most
    :data:`~.acquire.MAX_UPLOAD` bytes), ``/api/acquire/{id}`` (progress, then the answer),
    ``/api/acquire/{id}/{target|acquired|single|mask|sheet}.png``; websocket ``/ws?tab=ID``. Errors in a
    request answer 400 (the package's input errors), 429 (too many jobs of the page waiting:
    :class:`~mitsuba_manifold.errors.BusyError`), their HTTP status, or 500 with one line (a bug;
    the traceback stays on the server's console).
    """
    handlers = {e: _bad_request for e in BAD_REQUEST}
    handlers[BusyError] = _busy  # too many jobs waiting: ask again later
    handlers[HTTPException] = _http_error
    handlers[Exception] = _server_error
    app = Starlette(
        routes=Api(explorer).routes(),
        exception_handlers=handlers,
        middleware=[
            Middleware(Guard, allow=allow, max_body=max_body, limits={"/api/acquire": MAX_UPLOAD})
        ],
    )
    app.state.explorer = explorer
    return app
