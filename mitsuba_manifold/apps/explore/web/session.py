"""One tab's websocket: requests tagged with their point, the newest of each kind answered.

The page sends JSON text messages ``{"type": KIND, "seq": n, "x": [...], ...}`` (``route``: ``a``, ``b``, ``steps``,
``kind``: the points of a path, :meth:`~.service.Explorer.route`) or, once per
pointer move, one combined ``{"type": "move", "seq": n, "x": [...], "want": [KIND, ...], ...}``
standing for one request of each wanted kind at that point. For every kind (:data:`KINDS`)
the session holds at most one waiting request: a newer one replaces it (a drag never
queues stale points) and each kind has its own worker, so a slow latent map never holds up
a frame. Every answer is a binary message ``[uint32 n][n bytes of JSON meta][payload]`` whose
meta repeats the request's ``seq`` and the point ``x`` it is for, so the page can drop an
answer that arrives after a newer one. ``"coarse": true`` (a drag running) asks for the cheap
answers: a table of every other texel, a map of a quarter of the pixels, a material without the
distance to the closest measured one, a frame whose L2+ part is summed, not denoised (also while
``"held": true``, the pointer still down); the page asks again in full when the drag rests. A
move's ``"map_coarse"``, when given, says whether its map is the coarse one instead (a drag on the
map stays in one slice: its map is asked for in full at once). A
full (denoised) frame has its own worker (:data:`FINAL`), denoised only where that changes the
8-bit image visibly (:meth:`~.service.Explorer.frame`'s ``rest``; else the drag's frame):
denoising takes several frames' time, and the first frames of the next drag do not wait for it
(a coarse frame drops a full one still waiting; one that comes after a newer frame was drawn,
the page drops by its ``seq``).

A path (``route``) is computed by the explorer's path thread (:class:`~.walks.Walks`); the
session waits for it without holding any other kind, sends its progress every
:data:`PROGRESS_EVERY` s (``{"type": "progress", "kind": "route", "route_seq", "seconds",
"evaluations"}``), stops waiting when a newer ``route`` request arrives, the page sends
``{"type": "cancel", "kind": "route"}`` (answered with the route's error "cancelled"; the path
stops at its next step unless another tab waits for it) or the tab goes away, and then releases
the path (a path nobody waits for is never started). The websocket's query names the tab
(``/ws?tab=ID``): when the tab's socket closes, the background renders the tab started with
that ``tab`` (references, refinements) are cancelled.

Malformed input never reaches a traceback: a bad request is answered with
``{"type": "error", "kind", "seq", "error"}``; a binary message or one larger than
:data:`~.guard.MAX_MESSAGE` closes the websocket with code 1003 or 1009 and a reason.
"""

import asyncio
import json
import struct
import sys
import traceback

from starlette.concurrency import run_in_threadpool
from starlette.websockets import WebSocketDisconnect

from ....errors import InputError, UnknownMaterialError
from ..service import show
from .guard import MAX_MESSAGE

#: Kinds of request, and the order in which they are started when several wait.
KINDS = ("frame", "table", "material", "snippet", "map", "path", "route")
#: The worker of full (denoised) frames; their answers are frames.
FINAL = "final"
#: What a ``cancel`` message may cancel.
CANCELS = ("route",)
#: Seconds between two progress messages of a path being computed.
PROGRESS_EVERY = 0.5
#: Kinds answered for a point ``x`` (tagged with it).
POINT_KINDS = ("frame", "table", "material", "snippet", "map")
#: What answers a bad request with an error message.
BAD_REQUEST = (InputError, UnknownMaterialError)
#: How a websocket whose tab went away fails (uvicorn's ClientDisconnected is an OSError).
GONE = (WebSocketDisconnect, OSError)
_MAX_SEQ = 2**53


def pack(meta, payload=b""):
    """One binary websocket message: JSON meta then payload."""
    head = json.dumps(meta).encode()
    return struct.pack("<I", len(head)) + head + payload


def _coarse(req):
    """Whether a frame request asks for the cheap frame of a drag (L2+ summed, not denoised)."""
    return req.get("coarse") is True or req.get("held") is True


def _shown(kind):
    return "frame" if kind == FINAL else kind


class Superseded(Exception):
    """A newer request of the same kind arrived while this one waited: no answer is sent."""


class _Cancelled(InputError):
    """The page cancelled the path it waited for (answered as the route's error)."""


class Closing(Exception):
    """The client broke the protocol: close the websocket with ``code`` and ``reason``."""

    def __init__(self, code, reason):
        super().__init__(reason)
        self.code, self.reason = code, reason[:120]


def parse(text):
    """The requests of one message: a list of ``(kind, request)``; raises InputError."""
    if len(text) > MAX_MESSAGE:
        raise Closing(1009, f"message of {len(text)} characters; at most {MAX_MESSAGE}")
    try:
        req = json.loads(text)
    except (ValueError, RecursionError):
        raise InputError(
            f"bad message {show(text, 80)}: expected JSON like "
            '{"type": "frame", "seq": 1, "x": [0.1, 0.2]}'
        ) from None
    if not isinstance(req, dict) or not isinstance(req.get("type"), str):
        raise InputError(f"bad message {show(text, 80)}: expected a JSON object with a 'type'")
    seq = req.get("seq")
    if seq is not None and (
        isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq <= _MAX_SEQ
    ):
        raise InputError(f"'seq' must be an integer in 0..2^53, got {show(seq)}")
    kind = req["type"]
    if kind == "cancel":
        if req.get("kind") not in CANCELS:
            raise InputError(
                f"'kind' of a cancel must be one of {list(CANCELS)}, got {show(req.get('kind'))}"
            )
        return [("cancel", req)]
    if kind == "move":
        want = req.get("want")
        if (
            not isinstance(want, list)
            or not want
            or not all(isinstance(k, str) and k in KINDS for k in want)
        ):
            raise InputError(
                f"'want' of a move must be a list of kinds from {list(KINDS)}, got {show(want)}"
            )
        return [(k, req) for k in dict.fromkeys(want)]
    if kind not in KINDS:
        raise InputError(
            f"unknown message type {show(kind)}; expected one of {list(KINDS)}, 'move' or 'cancel'"
        )
    return [(kind, req)]


class Session:
    """The websocket of one tab (see the module docstring)."""

    def __init__(self, ws, explorer):
        self.ws, self.ex = ws, explorer
        self.pending = {}
        self.wake = {k: asyncio.Event() for k in KINDS + (FINAL,)}
        self.lock = asyncio.Lock()  # one message at a time on the socket
        self.cancel_route = asyncio.Event()  # the page cancelled the path it waits for
        tab = ws.query_params.get("tab", "")
        self.tab = tab if isinstance(tab, str) and 0 < len(tab) <= 64 and tab.isascii() else None

    async def send(self, meta, payload=b""):
        async with self.lock:
            await self.ws.send_bytes(pack(meta, payload))

    async def run(self):
        await self.ws.accept()
        tasks = [asyncio.ensure_future(self.reader())] + [
            asyncio.ensure_future(self.worker(k)) for k in KINDS + (FINAL,)
        ]
        try:
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for t in tasks:
                t.cancel()
            if self.tab is not None:  # the tab went away: its renders are no one's any more
                self.ex.references.cancel_tab(self.tab)
        for t in tasks:  # a tab going away (also while an answer is sent) is no error
            if t.done() and not t.cancelled() and t.exception() is not None:
                e = t.exception()
                if isinstance(e, Closing):
                    await self.ws.close(code=e.code, reason=e.reason)
                elif not isinstance(e, GONE):
                    raise e

    async def reader(self):
        while True:
            message = await self.ws.receive()
            if message["type"] == "websocket.disconnect":
                return
            if message.get("text") is None:
                raise Closing(1003, "binary messages are not accepted: send JSON text")
            try:
                requests = parse(message["text"])
            except InputError as e:
                await self.send({"type": "error", "kind": None, "seq": None, "error": str(e)})
                continue
            for kind, req in requests:
                if kind == "cancel":  # the path waited for, or about to be
                    self.pending.pop("route", None)
                    self.cancel_route.set()
                    continue
                if kind == "route":
                    self.cancel_route.clear()
                if kind == "frame" and not _coarse(req):
                    kind = FINAL
                elif kind == "frame":  # a drag again: a full frame not yet started is stale
                    self.pending.pop(FINAL, None)
                self.pending[kind] = req  # replaces an older request of this kind not yet started
                self.wake[kind].set()

    async def worker(self, kind):
        while True:
            await self.wake[kind].wait()
            self.wake[kind].clear()
            while kind in self.pending:
                req = self.pending.pop(kind)
                seq = req.get("seq")
                try:
                    meta, payload = await self.answer(kind, req)
                except Superseded:
                    continue
                except BAD_REQUEST as e:
                    meta, payload = (
                        {"type": "error", "kind": _shown(kind), "seq": seq, "error": str(e)},
                        b"",
                    )
                except Exception as e:  # a bug: the console gets the traceback, the page one line
                    traceback.print_exc(file=sys.stderr)
                    meta, payload = (
                        {
                            "type": "error",
                            "kind": _shown(kind),
                            "seq": seq,
                            "error": f"internal error ({type(e).__name__}); see the server's console",
                        },
                        b"",
                    )
                await self.send(dict(meta, seq=seq), payload)

    async def wait_route(self, future, seq=None) -> dict:
        """The result of a path's ``future``, its progress sent meanwhile; raises
        :class:`Superseded` when a newer ``route`` request arrives first, InputError when the
        page cancels it (the caller's release then stops it). Never cancels ``future`` itself
        (other tabs may wait for it).
        """
        result = asyncio.wrap_future(future)
        newer = asyncio.ensure_future(self.wake["route"].wait())
        cancel = asyncio.ensure_future(self.cancel_route.wait())
        try:
            while True:
                await asyncio.wait(
                    {result, newer, cancel},
                    timeout=PROGRESS_EVERY,
                    return_when=asyncio.FIRST_COMPLETED,
                )
                if result.done() or newer.done() or cancel.done():
                    break
                progress = self.ex.walks.progress(future)
                if progress is not None:
                    await self.send(dict(progress, type="progress", kind="route", route_seq=seq))
        finally:
            newer.cancel()
            cancel.cancel()
        if result.done():
            return result.result()
        result.add_done_callback(lambda f: f.cancelled() or f.exception())  # nobody reads it now
        if self.cancel_route.is_set():
            raise _Cancelled("cancelled")
        raise Superseded()

    async def answer(self, kind, req):
        """``(meta, payload)`` of one request (raises InputError on bad input)."""
        ex = self.ex
        if kind == "path":
            cmd = await run_in_threadpool(
                ex.path_command,
                req.get("basis"),
                req.get("a"),
                req.get("b"),
                req.get("steps"),
                req.get("kind"),
            )
            return {"type": "path", "command": cmd, "a": req.get("a"), "b": req.get("b")}, b""
        if (
            kind == "route"
        ):  # computed in the paths' own thread: waits without holding any other kind
            future = await run_in_threadpool(
                ex.route, req.get("a"), req.get("b"), req.get("steps"), req.get("kind")
            )
            stop = False
            try:
                route = await self.wait_route(future, req.get("seq"))
            except _Cancelled:
                stop = True
                raise
            finally:
                ex.walks.release(future, stop=stop)
            return dict(route, type="route"), b""
        x = ex.point(req.get("x"), "x")
        kind = _shown(kind)
        tag = {"type": kind, "x": [float(v) for v in x]}
        if kind == "frame":
            exposure = ex.number(req.get("exposure"), "exposure", -20, 20, 0.0)
            coarse = _coarse(req)
            if coarse:  # a drag: no refinement nor reference competes with its frames for the CPU
                ex.references.supersede_refine()
                ex.references.hold()
            data, meta = await run_in_threadpool(  # at rest: denoised where that shows
                ex.frame,
                req.get("basis"),
                x,
                exposure,
                req.get("format", "jpeg"),
                coarse,
                not coarse,
            )
            return dict(meta, exposure=exposure, basis=ex.key(req.get("basis")), **tag), data
        if kind == "material":
            with_slice, live = req.get("slice", True) is not False, req.get("coarse") is True
            return dict(await run_in_threadpool(ex.material, x, with_slice, live), **tag), b""
        if kind == "table":
            data, meta = await run_in_threadpool(ex.preview_table, x, req.get("coarse") is True)
            return dict(meta, **tag), data
        if kind == "snippet":
            return dict(ex.snippets(x, req.get("folder")), **tag), b""
        dims, extent = req.get("dims", [0, 1]), req.get("extent")
        coarse = req.get("map_coarse", req.get("coarse")) is True
        key = ex.map_key(dims, x, extent, coarse)
        data, meta = await run_in_threadpool(
            ex.map_png, dims, x, extent, coarse, lambda: self.stale_map(key)
        )
        return dict(meta, **tag), data

    def stale_map(self, key=None):
        """Raises :class:`Superseded` when a newer request for another map than ``key``
        (:meth:`~.service.Explorer.map_key`; None: any map) waits: the map being made is
        abandoned, its slice or zoom is not the page's any more. A request for the same map lets
        it go on (it is answered from the kept maps). Called from the map's thread.
        """
        req = self.pending.get("map")
        if req is None:
            return
        if key is not None:
            try:
                x = self.ex.point(req.get("x"), "x")
                dims, extent = req.get("dims", [0, 1]), req.get("extent")
                coarse = req.get("map_coarse", req.get("coarse")) is True
                if self.ex.map_key(dims, x, extent, coarse) == key:
                    return
            except (InputError, UnknownMaterialError):  # a bad request: its error comes after
                pass
        raise Superseded()
