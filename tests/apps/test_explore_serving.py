"""The explorer's server under misbehaving connections (serving.py): requests never finished are
closed after the deadline, connections beyond the cap are refused with a 503, the log collapses
repeats. Raw sockets on 127.0.0.1 against uvicorn running the explorer's protocol."""

import logging
import socket
import threading
import time

import pytest

pytest.importorskip("uvicorn")
pytest.importorskip("starlette")

from mitsuba_manifold.apps.explore.web.serving import RepeatFilter, protocol  # noqa: E402

BIG = 64 << 20  # a response far larger than the sockets' buffers


@pytest.fixture
def serve():
    """``serve(deadline, cap)``: a uvicorn server of a one-route app on 127.0.0.1 in a thread,
    with the explorer's protocol; returns its port. Stopped at the end of the test."""
    import uvicorn
    from starlette.applications import Starlette
    from starlette.responses import PlainTextResponse, Response
    from starlette.routing import Route

    servers = []

    def start(deadline, cap, write_deadline=30.0):
        async def hello(request):
            await request.body()
            return PlainTextResponse("hello")

        async def big(request):
            return Response(b"x" * BIG, media_type="application/octet-stream")

        sock = socket.socket()
        sock.bind(("127.0.0.1", 0))
        sock.listen(128)
        config = uvicorn.Config(
            Starlette(routes=[Route("/", hello, methods=["GET", "POST"]), Route("/big", big)]),
            http=protocol(deadline, cap, write_deadline),
            log_level="critical",
            timeout_keep_alive=60,  # longer than the deadline: the deadline closes idle ones
        )
        server = uvicorn.Server(config)
        t = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
        t.start()
        end = time.monotonic() + 20
        while not server.started and time.monotonic() < end:
            time.sleep(0.02)
        assert server.started
        servers.append((server, t, sock))
        return sock.getsockname()[1]

    yield start
    for server, t, sock in servers:
        server.should_exit = True
        t.join(10)
        sock.close()


def _get(port, timeout=5):
    with socket.create_connection(("127.0.0.1", port), timeout=timeout) as s:
        s.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        return _read_all(s)


def _read_all(s):
    """Everything the server sends until it closes (raises socket.timeout if it does not)."""
    out = b""
    while True:
        try:
            chunk = s.recv(65536)
        except ConnectionResetError:
            return out
        if not chunk:
            return out
        out += chunk


def test_unfinished_requests_are_closed_and_the_server_still_answers(serve):
    port = serve(deadline=1.0, cap=100)
    socks = []
    try:
        for k in range(40):  # half a request line, headers without their end, a body cut short
            s = socket.create_connection(("127.0.0.1", port), timeout=10)
            s.sendall(
                (b"GET / HTT", b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nX-A: b\r\n")[k % 2]
                if k % 3
                else b"POST / HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 100\r\n\r\nabc"
            )
            socks.append(s)
        assert _get(port).startswith(b"HTTP/1.1 200")  # meanwhile the server answers
        for s in socks:  # each is closed by the server, saying why (408), none left open
            reply = _read_all(s)
            assert reply.startswith(b"HTTP/1.1 408"), reply[:80]
        assert _get(port).startswith(b"HTTP/1.1 200")
    finally:
        for s in socks:
            s.close()


def test_a_slow_client_sending_a_byte_at_a_time_is_closed_too(serve):
    """Bytes trickling in do not extend the deadline (a keep-alive timer would be reset by each)."""
    port = serve(deadline=1.0, cap=100)
    request = b"GET / HTTP/1.1\r\n" + b"".join(b"X-%d: 1\r\n" % k for k in range(100))
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.settimeout(0.2)
        reply = None
        for k, byte in enumerate(request[:40]):  # noqa: B007  # a byte every 0.2 s
            try:
                s.sendall(bytes([byte]))
                reply = s.recv(1024)  # times out while the server still waits
                break
            except socket.timeout:
                continue
            except OSError:
                reply = b""
                break
        assert reply is not None and (reply == b"" or reply.startswith(b"HTTP/1.1 408")), reply
        assert k < 30, k  # closed after about 1 s of it (5 bytes), long before its end


def test_connections_beyond_the_cap_get_a_clear_refusal(serve):
    port = serve(deadline=30.0, cap=20)
    socks = []
    try:
        for _ in range(20):
            socks.append(socket.create_connection(("127.0.0.1", port), timeout=10))
        time.sleep(0.3)  # accepted by the server
        with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
            reply = _read_all(s)  # sending nothing: refused within a second
        assert reply.startswith(b"HTTP/1.1 503") and b"20 connections open" in reply, reply
        for _ in range(5):  # a request sent at once: its 503 is read, not lost to a reset
            with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
                s.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
                assert _read_all(s).startswith(b"HTTP/1.1 503")
        for s in socks[:5]:  # freed: new connections are answered again
            s.close()
        time.sleep(0.3)
        assert _get(port).startswith(b"HTTP/1.1 200")
    finally:
        for s in socks:
            s.close()


def test_a_complete_request_and_a_keep_alive_connection_are_answered(serve):
    """The deadline is per request: a kept-alive connection gets its second answer."""
    port = serve(deadline=1.0, cap=100)
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        for _ in range(2):
            s.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            head = b""
            while not head.endswith(b"hello"):
                chunk = s.recv(65536)
                assert chunk, head  # not closed: the response comes in full
                head += chunk
            assert head.startswith(b"HTTP/1.1 200") and head.endswith(b"hello"), head
            time.sleep(0.6)  # within the deadline each time
        # then idle: closed at the deadline without a word (a 408 there could be read as the
        # answer to a request a client sends just then)
        assert _read_all(s) == b""


def test_a_response_its_client_never_reads_is_dropped(serve):
    port = serve(deadline=1.0, cap=100, write_deadline=1.0)
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(b"GET /big HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        time.sleep(4)  # reads nothing: the server's writes stall, then it drops the connection
        got = len(_read_all(s))
    assert 0 < got < BIG // 2, got
    assert _get(port).startswith(b"HTTP/1.1 200")


def test_repeated_log_records_are_collapsed():
    now = [0.0]
    f = RepeatFilter(window=10.0, clock=lambda: now[0])
    logger = logging.getLogger("test_explore_serving.flood")
    logger.propagate = False
    got = []

    class Keep(logging.Handler):
        def emit(self, record):
            got.append(record.getMessage())

    logger.addHandler(Keep())
    logger.addFilter(f)
    for k in range(10000):  # a flood: one socket error per turn of the loop
        now[0] = k * 1e-3
        logger.error("socket.accept() out of system resource\nsocket: <fd=%d>", k)
    logger.warning("another message")
    now[0] = 30.0
    logger.error("socket.accept() out of system resource\nsocket: <fd=%d>", 1)
    assert len(got) == 3, got
    assert "9999 more like this" in got[2] and got[1] == "another message"
