"""The explorer's web app (Starlette): the page, a JSON/binary API and a websocket for drags.

Drags go over one websocket per tab (:mod:`.session`: requests tagged with their point, the
newest of each kind answered). Everything else is plain HTTP (:func:`create_app` lists the
routes). Every request passes :class:`~.guard.Guard` first: the Host/Origin allow-list
(DNS rebinding, other sites) and the body size limit. Errors in a request answer 400 with
``{"error": message}`` (one line); no traceback reaches the page.
"""

import json
import os
import re

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.exceptions import HTTPException
from starlette.middleware import Middleware
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route, WebSocketRoute
from starlette.staticfiles import StaticFiles

from ...errors import InputError
from . import encode
from .guard import MAX_BODY, Guard
from .service import show
from .session import BAD_REQUEST, Session

STATIC = os.path.join(os.path.dirname(os.path.abspath(__file__)), "static")
_JOB_ID = re.compile(r"^r[0-9]{1,9}$")


def _query(request, key, default=None):
    return request.query_params.get(key, default)


def create_app(explorer, allow=None, max_body=MAX_BODY):
    """The Starlette app serving ``explorer`` (a :class:`~.service.Explorer`).

    ``allow``: the :class:`~.guard.AllowList` of hosts and origins (default: ``127.0.0.1``,
    ``localhost`` and ``[::1]`` on any port); ``max_body``: largest request body in bytes.

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
        import base64
        dims = _query(request, "dims", "0,1")
        center = x_of(request) if _query(request, "x") else ex.manifold.latent.mean(axis=0)
        png, meta = await run_in_threadpool(ex.map_png, dims, center, _query(request, "extent"))
        return JSONResponse(dict(meta, png="data:image/png;base64," + base64.b64encode(png).decode()))

    async def snippet(request):
        return JSONResponse(ex.snippets(x_of(request)))

    async def path(request):
        cmd = ex.path_command(_query(request, "basis"), _query(request, "a", ""), _query(request, "b", ""),
                              _query(request, "steps"))
        return JSONResponse({"command": cmd})

    async def reference_start(request):
        try:   # the body was read by Guard, at most max_body bytes
            body = json.loads(await request.body())
        except (ValueError, RecursionError):
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
            raise InputError(f"unknown reference job {show(job_id)}")
        return job

    async def reference_status(request):
        return JSONResponse(job_of(request).status())

    async def reference_image(request):
        job = job_of(request)
        exposure = ex.number(_query(request, "exposure"), "exposure", -20, 20, 0.0)
        png = await run_in_threadpool(ex.reference_image, job.id, request.path_params["which"], exposure)
        return Response(png, media_type="image/png")

    async def websocket(ws):
        await Session(ws, ex).run()   # the handshake passed Guard's allow-list

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
    app = Starlette(routes=routes, exception_handlers=handlers,
                    middleware=[Middleware(Guard, allow=allow, max_body=max_body)])
    app.state.explorer = ex
    return app
