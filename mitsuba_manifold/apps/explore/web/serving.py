"""How the explorer's server holds up under connections that misbehave: deadlines, a cap, a quiet log.

uvicorn keeps a connection open as long as its client keeps it, and reads a request's headers
for as long as they take: a client that opens connections and never finishes a request holds
a socket each, forever, until the server runs out of them (and asyncio then logs the failed
``accept`` on every turn of its loop). :func:`protocol` makes the HTTP protocol class the
explorer runs uvicorn with (h11's, whatever else is installed), which

- closes a connection whose request (headers and body) is not complete within ``deadline``
  seconds of the connection opening or of its previous response (``408``, then closed);
- refuses a connection beyond ``max_connections`` open at once (websockets included) with a
  ``503`` naming the limit once its request's headers are in (at most a second later), and
  closes it;
- drops a connection whose client has read nothing of its response for ``write_deadline``
  seconds (a response waits in memory for its client).

:class:`RepeatFilter` collapses repeated log records (one per ``window`` seconds per message,
then a count of those left out), so that no fault can fill the console or the disk.
"""

import logging
import threading
import time

#: Seconds a connection has to send a complete request (after opening, or after a response).
REQUEST_DEADLINE = 5.0
#: Seconds a response may wait for a client that reads none of it (then the connection is dropped).
WRITE_DEADLINE = 30.0
#: Connections open at once (HTTP and websockets, every page together) before new ones get 503.
MAX_CONNECTIONS = 256
#: Seconds between two records of the same message in the console (the others are counted).
LOG_WINDOW = 10.0


def _reply(status, reason, text) -> bytes:
    body = (text + "\n").encode()
    return (
        f"HTTP/1.1 {status} {reason}\r\ncontent-type: text/plain; charset=utf-8\r\n"
        f"content-length: {len(body)}\r\nconnection: close\r\n\r\n"
    ).encode() + body


def protocol(  # noqa: C901  counts the methods of the class it defines (closing over the limits)
    deadline=REQUEST_DEADLINE, max_connections=MAX_CONNECTIONS, write_deadline=WRITE_DEADLINE
) -> type:
    """The h11 HTTP protocol of uvicorn with a request deadline, a connection cap and a deadline
    on responses the client does not read (module doc); pass it as ``uvicorn.Config(http=...)``.

    The subclass is defined here: it closes over the limits given and over uvicorn's protocol,
    which is imported only when a server starts.
    """
    import h11
    from uvicorn.protocols.http.h11_impl import H11Protocol

    if not deadline > 0 or not write_deadline > 0 or int(max_connections) < 1:
        raise ValueError(
            "deadline and write_deadline must be > 0 and max_connections >= 1, got "
            f"{deadline}, {write_deadline}, {max_connections}"
        )
    refusal = _reply(
        503,
        "Service Unavailable",
        f"the explorer has {max_connections} connections open, its limit; close some tabs or "
        "try again",
    )

    class GuardedH11Protocol(H11Protocol):
        """h11's protocol, with a deadline per request and a cap on open connections."""

        def connection_made(self, transport) -> None:
            super().connection_made(transport)
            self._waiting_since = self.loop.time()
            self._stalled_since = None
            self._deadline = None
            self._refused = None
            self._answered = 0
            if len(self.connections) > max_connections:
                # refused: the 503 once the request's headers are read (closing a socket with
                # unread data resets it, and the client would never see why), within a second
                self.connections.discard(self)
                self._refused = b""
                self._deadline = self.loop.call_later(min(1.0, deadline), self._refuse)
                return
            self._arm(deadline)

        def data_received(self, data) -> None:
            if self._refused is None:
                super().data_received(data)
                return
            self._refused = (self._refused + data)[-4:]
            if b"\r\n\r\n" in self._refused or b"\n\n" in self._refused:
                self._refuse()

        def _refuse(self) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None
            if not self.transport.is_closing():
                self.transport.write(refusal)
                self.transport.close()

        def _arm(self, seconds) -> None:
            self._deadline = self.loop.call_later(seconds, self._check_deadline)

        def _receiving(self) -> bool:
            """Whether the client owes the rest of a request (none begun, or one half sent)."""
            return self.conn.their_state in (h11.IDLE, h11.SEND_BODY) and (
                self.cycle is None
                or self.cycle.response_complete
                or self.conn.their_state is h11.SEND_BODY
            )

        def _check_deadline(self) -> None:
            self._deadline = None
            if self.transport.is_closing() or self.transport.get_protocol() is not self:
                return  # closed, or a websocket now (its protocol has its own pings and limits)
            now = self.loop.time()
            if not self.flow.write_paused:
                self._stalled_since = None
            elif self._stalled_since is None:
                self._stalled_since = now
            elif now - self._stalled_since >= write_deadline:
                self.transport.abort()  # its client reads nothing: the response is dropped
                return
            if not self._receiving() or self.transport.get_write_buffer_size():
                # the request is in and answered, or its response still being sent: the next
                # request's deadline starts once it is
                self._waiting_since = None
                self._arm(min(deadline, write_deadline))
                return
            if self._waiting_since is None:
                self._waiting_since = now
            left = self._waiting_since + deadline - now
            if left > 0:
                self._arm(left)
                return
            idle = self._answered and not self.conn.trailing_data[0]  # kept alive, nothing sent
            if (self.conn.their_state is h11.IDLE and not idle) or not (
                self.cycle is None or self.cycle.response_started
            ):  # no request yet, or a body cut short and no answer begun: say why it is closed
                self.transport.write(
                    _reply(
                        408,
                        "Request Timeout",
                        f"the request was not complete within {deadline:g} s",
                    )
                )
            self.transport.close()  # the app reading a body cut short sees the disconnect

        def on_response_complete(self) -> None:
            self._answered += 1
            super().on_response_complete()
            self._waiting_since = self.loop.time()  # the next request has its own deadline

        def connection_lost(self, exc) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None
            if self._refused is not None:
                return  # never counted, nothing begun
            super().connection_lost(exc)

    return GuardedH11Protocol


class RepeatFilter(logging.Filter):
    """A logging filter passing the first record of each message (its format string, logger and
    exception type) once per ``window`` seconds; the next one passed after a pause says how many
    were left out meanwhile.
    """

    def __init__(self, window=LOG_WINDOW, clock=time.monotonic) -> None:
        super().__init__()
        self.window, self.clock = float(window), clock
        self._seen: dict = {}  # key -> [time passed, records left out since]
        self._lock = threading.Lock()

    def filter(self, record) -> bool:
        exc = record.exc_info[0].__name__ if record.exc_info and record.exc_info[0] else None
        # the first line: asyncio's messages go on with the socket or task they are about
        key = (record.name, record.levelno, str(record.msg).split("\n", 1)[0][:200], exc)
        now = self.clock()
        with self._lock:
            seen = self._seen.get(key)
            if seen is not None and now - seen[0] < self.window:
                seen[1] += 1
                return False
            left_out = seen[1] if seen is not None else 0
            self._seen[key] = [now, 0]
            if len(self._seen) > 1024:  # messages that vary forever: the oldest forgotten
                for k in sorted(self._seen, key=lambda k: self._seen[k][0])[:512]:
                    del self._seen[k]
        if left_out:
            record.msg = (
                f"{record.msg} [{left_out} more like this in the last {self.window:g} s, not shown]"
            )
        return True


#: The loggers the explorer's server writes to (uvicorn's and asyncio's).
SERVER_LOGGERS = ("asyncio", "uvicorn", "uvicorn.error", "uvicorn.access")


def quiet_logs(window=LOG_WINDOW) -> RepeatFilter:
    """Put a :class:`RepeatFilter` on the server's loggers and on their handlers (a record is
    filtered where it is made, and where it is written when it comes from a logger below);
    returns it. Call it after uvicorn has configured its loggers.
    """
    f = RepeatFilter(window)
    for name in SERVER_LOGGERS:
        logger = logging.getLogger(name)
        logger.addFilter(f)
        for h in logger.handlers:
            h.addFilter(f)
    return f


def server_blas_threads(cores=None) -> int:
    """BLAS threads of the explorer's server: the machine's cores less two (the browser showing
    the page, and the frames), at least one.
    """
    import os

    cores = os.cpu_count() if cores is None else cores
    return max(1, (cores or 1) - 2)


def make_server(app, max_message):
    """The uvicorn server of the explorer's ``app``: the protocol of :func:`protocol` (deadlines,
    a cap on connections), websocket messages up to ``max_message`` bytes, no per-message deflate
    (frames are JPEG or raw pixels: compressing them would cost more time than it saves), no
    pings, a second to shut down.
    """
    import uvicorn

    return uvicorn.Server(
        uvicorn.Config(
            app,
            http=protocol(),
            log_level="warning",
            timeout_graceful_shutdown=1,
            ws_ping_interval=None,
            ws_per_message_deflate=False,
            ws_max_size=max_message,
        )
    )
