"""Who may talk to the explorer, and how much: the Host/Origin allow-list and size limits.

A page of another site must not drive the explorer (start renders, read frames). Comparing
the ``Origin`` header with the ``Host`` header is not enough: with DNS rebinding a page of
``evil.example`` reaches this server under the name ``evil.example``, so both headers name
the attacker's host. :class:`AllowList` therefore names the hosts the server answers to
(``127.0.0.1``, ``localhost`` and ``[::1]`` with its port, the address it was started on, and
origins given with ``--allow-origin``); a request with any other ``Host`` is refused (403),
and an ``Origin`` header, when a browser sends one, must be one of the allowed origins
exactly, scheme and port included. :class:`Guard` is the ASGI middleware applying it to
every HTTP request and websocket handshake, and reading request bodies with a size limit
(:data:`MAX_BODY`) before any handler parses them.
"""

import json
import re
from urllib.parse import urlsplit

#: Largest request body (bytes) and websocket message (characters) accepted.
MAX_BODY = 64 * 1024
MAX_MESSAGE = 64 * 1024
#: Names of this machine's loopback interface.
LOCAL_NAMES = ("127.0.0.1", "localhost", "[::1]")
DEFAULT_PORTS = {"http": 80, "https": 443, "ws": 80, "wss": 443}
_HOST = re.compile(r"^(\[[0-9a-f:.]+\]|[a-z0-9.\-_]+)(?::([0-9]{1,5}))?$")


def _name(host):
    """Lower-case host name; IPv6 addresses in brackets (as in a Host header)."""
    host = str(host).strip().lower()
    return f"[{host}]" if ":" in host and not host.startswith("[") else host


def parse_host(text, default_port=80):
    """``(name, port)`` of a Host header value, or None when it is not one."""
    m = _HOST.match(str(text or "").strip().lower())
    if not m:
        return None
    port = int(m.group(2)) if m.group(2) else default_port
    return (m.group(1), port) if port is None or port <= 65535 else None


def parse_origin(text):
    """``(scheme, name, port)`` of an origin like ``http://127.0.0.1:8765``, or None."""
    try:
        parts = urlsplit(str(text).strip())
        scheme = parts.scheme.lower()
        if (
            scheme not in DEFAULT_PORTS
            or parts.path not in ("", "/")
            or parts.query
            or parts.username
        ):
            return None
        host = parse_host(parts.netloc, DEFAULT_PORTS[scheme])
    except ValueError:
        return None
    return None if host is None else (scheme,) + host


class AllowList:
    """The hosts and origins the explorer answers to.

    Parameters
    ----------
    port : int, optional
        The server's port; None: any port (for :func:`create_app` used without a server,
        e.g. by tests; an Origin must then name the port of the request's Host).
    hosts : iterable of str
        Host names (or addresses) allowed with ``port`` (default: :data:`LOCAL_NAMES`).
    origins : iterable of str
        Further origins, exactly (``https://explore.example:443``): each also allows its host.
    """

    def __init__(self, port=None, hosts=LOCAL_NAMES, origins=()):
        self.port = None if port is None else int(port)
        self.hosts = {_name(h) for h in hosts}
        self.origins = set()
        for text in origins:
            origin = parse_origin(text)
            if origin is None:
                raise ValueError(
                    f"allowed origin {text!r} must be like http://name:port (scheme, host, "
                    "optional port; nothing else)"
                )
            self.origins.add(origin)

    @classmethod
    def for_server(cls, host, port, origins=(), bound=None):
        """The allow-list of a server started with ``--host host --port port`` (the port it
        got), listening on address ``bound``, with ``--allow-origin`` values ``origins``.
        """
        names = set(LOCAL_NAMES) | {_name(host)} | ({_name(bound)} if bound else set())
        return cls(port, names, origins)

    def host_ok(self, header):
        """Whether a request with this Host header is for this server."""
        host = parse_host(header, default_port=None)
        if host is None:
            return False
        name, port = host
        if name in self.hosts and self.port in (None, 80 if port is None else port):
            return (
                True  # a Host without a port: the scheme's default (80, or 443 behind a TLS proxy)
            )
        return any(
            o[1] == name and (o[2] == port or (port is None and o[2] == DEFAULT_PORTS[o[0]]))
            for o in self.origins
        )

    def origin_ok(self, header, host_header):
        """Whether a browser's Origin header (None: not sent, as for same-origin GETs) is allowed."""
        if header is None:
            return True
        origin = parse_origin(header)
        if origin is None:
            return False
        if origin in self.origins:
            return True
        port = self.port if self.port is not None else (parse_host(host_header) or (None, None))[1]
        return origin[0] == "http" and origin[1] in self.hosts and origin[2] == port

    def describe(self):
        ports = f":{self.port}" if self.port is not None else ""
        return sorted(f"http://{h}{ports}" for h in self.hosts) + sorted(
            f"{s}://{h}:{p}" for s, h, p in self.origins
        )


def _headers(scope):
    out = {}
    for k, v in scope.get("headers", ()):
        out.setdefault(k.decode("latin-1").lower(), v.decode("latin-1"))
    return out


def refusal(scope, allow):
    """Why a request is refused (a one-line message), or None when it is allowed."""
    h = _headers(scope)
    if not allow.host_ok(h.get("host")):
        return (
            f"refused: Host {str(h.get('host'))[:60]!r} is not this server's (allowed: "
            f"{', '.join(allow.describe())}; start with --allow-origin to add one)"
        )
    if not allow.origin_ok(h.get("origin"), h.get("host")):
        return f"refused: a page of origin {str(h.get('origin'))[:60]!r} may not use this server (cross-origin request)"
    return None


async def _answer(send, status, message):
    body = json.dumps({"error": message}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class Guard:
    """ASGI middleware: the allow-list on every request and handshake, and bodies read with
    a limit (413 past ``max_body`` bytes, before the app sees any of it; ``limits``: path ->
    the limit of that path's bodies instead, e.g. an upload's).
    """

    def __init__(self, app, allow=None, max_body=MAX_BODY, limits=None):
        self.app = app
        self.allow = allow if allow is not None else AllowList()
        self.max_body = int(max_body)
        self.limits = {str(k): int(v) for k, v in (limits or {}).items()}

    async def __call__(self, scope, receive, send):
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        why = refusal(scope, self.allow)
        if why is not None:
            if scope["type"] == "websocket":  # before accepting: the handshake answers 403
                await receive()
                return await send({"type": "websocket.close", "code": 1008, "reason": why[:120]})
            return await _answer(send, 403, why)
        if scope["type"] == "http" and scope["method"] not in ("GET", "HEAD"):
            limit = self.limits.get(scope.get("path", ""), self.max_body)
            length = _headers(scope).get("content-length", "0").strip()
            if not length.isdigit() or int(length) > limit:
                return await _answer(
                    send,
                    413 if length.isdigit() else 400,
                    f"request body larger than {limit} bytes refused"
                    if length.isdigit()
                    else "bad Content-Length header",
                )
            body, more, size = [], True, 0
            while more:
                message = await receive()
                if message["type"] == "http.disconnect":
                    return
                chunk = message.get("body", b"")
                size += len(chunk)
                if size > limit:
                    return await _answer(
                        send, 413, f"request body larger than {limit} bytes refused"
                    )
                body.append(chunk)
                more = message.get("more_body", False)
            return await self.app(scope, _replay(b"".join(body), receive), send)
        return await self.app(scope, receive, send)


def _replay(body, receive):
    """An ASGI ``receive`` giving ``body`` (already read) once, then the connection's own."""
    replay = [{"type": "http.request", "body": body, "more_body": False}]

    async def again():
        return replay.pop() if replay else await receive()

    return again
