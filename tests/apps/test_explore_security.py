"""tools/explore.py under attack: the Host/Origin allow-list (DNS rebinding, other sites, other
schemes), size limits, and malformed input of every kind over HTTP and the websocket, with
hypothesis fuzzers: a 400 (or 403/404/405/413) with a one-line JSON error, or a websocket
error message / close with a code and reason, never a traceback or a 500."""

import json
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytest.importorskip("starlette")
pytest.importorskip("mitsuba")
pytestmark = pytest.mark.render

import test_explore  # noqa: E402
from starlette.testclient import TestClient  # noqa: E402
from starlette.websockets import WebSocketDisconnect  # noqa: E402

from mitsuba_manifold.apps.explore import create_app  # noqa: E402
from mitsuba_manifold.apps.explore.web.guard import (
    MAX_BODY,
    MAX_MESSAGE,
    AllowList,
    parse_host,
    parse_origin,
)  # noqa: E402
from mitsuba_manifold.apps.explore.web.session import Closing, parse  # noqa: E402
from mitsuba_manifold.errors import InputError  # noqa: E402

PORT = 8799
LOCAL = f"127.0.0.1:{PORT}"
HUGE = 10**400  # 401 digits: float() overflows
small_basis, explorer = (
    test_explore.small_basis,
    test_explore.explorer,
)  # module fixtures: a rendered basis
SUITE = settings(max_examples=120, deadline=None, suppress_health_check=list(HealthCheck))


@pytest.fixture(scope="module")
def app(explorer):
    return create_app(explorer, AllowList.for_server("127.0.0.1", PORT))


@pytest.fixture(scope="module")
def client(app):
    with TestClient(app, base_url=f"http://{LOCAL}") as c:
        yield c


@pytest.fixture
def no_renders(explorer, monkeypatch):
    """Reference requests that pass validation are recorded, not rendered (fuzzing sends many)."""
    started = []

    def submit(name, basis, scene, manifold_path, x, spp, img, tab=None):
        started.append((name, list(x), spp))
        from mitsuba_manifold.apps.explore.reference import Job

        return Job(id=f"r{len(started)}", basis=name, x=list(map(float, x)), spp=spp)

    monkeypatch.setattr(explorer.references, "submit", submit)
    return started


def _ws(client, host=LOCAL, origin=None):
    headers = {"host": host}
    if origin:
        headers["origin"] = origin
    return client.websocket_connect("/ws", headers=headers)


def _unpack(msg):
    n = struct.unpack("<I", msg[:4])[0]
    return json.loads(msg[4 : 4 + n]), msg[4 + n :]


def _one_line_error(r, codes=(400,)):
    assert r.status_code in codes, (r.status_code, r.text[:300])
    body = r.json()
    assert (
        set(body) == {"error"} and isinstance(body["error"], str) and "\n" not in body["error"]
    ), body
    assert "Traceback" not in body["error"]
    return body["error"]


# ---------------------------------------------------------------- allow-list


def test_allow_list_parsing():
    assert parse_host("127.0.0.1:8799") == ("127.0.0.1", 8799)
    assert parse_host("[::1]:80") == ("[::1]", 80) and parse_host("LocalHost") == ("localhost", 80)
    for bad in ("", None, "a b", "host:99999", "host:12:3", "h@x:1", "[::1"):
        assert parse_host(bad) is None, bad
    assert parse_origin("https://x.example") == ("https", "x.example", 443)
    for bad in ("null", "file://", "http://x/path", "ftp://x", "http://u@x", "x.example"):
        assert parse_origin(bad) is None, bad
    allow = AllowList.for_server("0.0.0.0", PORT, ["https://explore.example"])
    assert (
        allow.host_ok(LOCAL)
        and allow.host_ok(f"localhost:{PORT}")
        and allow.host_ok(f"[::1]:{PORT}")
    )
    assert allow.host_ok(f"0.0.0.0:{PORT}") and allow.host_ok("explore.example:443")
    assert not allow.host_ok("127.0.0.1:1234") and not allow.host_ok(f"evil.example:{PORT}")
    assert allow.origin_ok("https://explore.example", "explore.example:443")
    assert not allow.origin_ok("http://explore.example:443", "explore.example:443")  # scheme
    assert allow.origin_ok(f"http://localhost:{PORT}", LOCAL) and allow.origin_ok(None, LOCAL)
    assert not allow.origin_ok(f"https://127.0.0.1:{PORT}", LOCAL) and not allow.origin_ok(
        "null", LOCAL
    )
    with pytest.raises(ValueError, match="allowed origin"):
        AllowList(origins=["http://x.example/path"])


def test_dns_rebinding_and_other_sites_are_refused(client, no_renders):
    """The issue's cases: Host evil.example with its own Origin (DNS rebinding), another
    scheme, another port, no Host: 403 on HTTP and on the websocket handshake."""
    body = {"x": "chrome", "spp": 4}
    rebinding = {"host": f"evil.example:{PORT}", "origin": f"http://evil.example:{PORT}"}
    for headers in (
        rebinding,
        {"host": f"evil.example:{PORT}"},
        {"host": "127.0.0.1:1"},
        {"host": LOCAL, "origin": f"https://127.0.0.1:{PORT}"},
        {"host": LOCAL, "origin": f"http://127.0.0.1:{PORT + 1}"},
        {"host": LOCAL, "origin": "http://evil.example"},
        {"host": LOCAL, "origin": "null"},
    ):
        assert "refused" in _one_line_error(
            client.post("/api/reference", json=body, headers=headers), (403,)
        )
        assert "refused" in _one_line_error(client.get("/api/info", headers=headers), (403,))
        assert client.get("/", headers=headers).status_code == 403
        with pytest.raises(WebSocketDisconnect) as closed:
            with _ws(client, headers["host"], headers.get("origin")) as ws:
                ws.receive_bytes()
        assert closed.value.code == 1008
    assert not no_renders
    for host, origin in (
        (LOCAL, None),
        (LOCAL, f"http://127.0.0.1:{PORT}"),
        (f"localhost:{PORT}", f"http://localhost:{PORT}"),
        (f"[::1]:{PORT}", f"http://[::1]:{PORT}"),
    ):
        r = client.post(
            "/api/reference",
            json=body,
            headers={"host": host, **({"origin": origin} if origin else {})},
        )
        assert r.status_code == 200, r.text
        with _ws(client, host, origin) as ws:
            ws.send_text(json.dumps({"type": "snippet", "seq": 1, "x": "chrome"}))
            assert _unpack(ws.receive_bytes())[0]["type"] == "snippet"
    assert len(no_renders) == 4


def test_allow_origin_adds_an_origin_exactly(explorer):
    app = create_app(explorer, AllowList.for_server("127.0.0.1", PORT, ["https://explore.example"]))
    with TestClient(app, base_url="https://explore.example") as c:
        assert c.get("/api/info", headers={"origin": "https://explore.example"}).status_code == 200
        assert c.get("/api/info", headers={"origin": "http://explore.example"}).status_code == 403


def test_cli_refuses_a_bad_allow_origin(small_basis, capsys):
    from mitsuba_manifold.apps.cli.explore import main

    assert main(["--basis", small_basis, "--port", "0", "--allow-origin", "evil.example"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: --allow-origin") and err.count("\n") == 1


# ---------------------------------------------------------------- HTTP input


def test_bodies_are_size_limited_before_parsing(client, no_renders):
    big = json.dumps({"x": "chrome", "pad": "a" * MAX_BODY}).encode()
    assert "larger than" in _one_line_error(client.post("/api/reference", content=big), (413,))

    def stream():  # no Content-Length: counted while reading
        for _ in range(100):
            yield b" " * 4096

    assert "larger than" in _one_line_error(client.post("/api/reference", content=stream()), (413,))
    assert not no_renders


@pytest.mark.parametrize(
    "body",
    [
        "[" * 30000 + "]" * 30000,
        '{"x": ' + "[" * 20000 + "]" * 20000 + "}",
        json.dumps({"x": [HUGE, 0]}),
        json.dumps({"x": "chrome", "spp": HUGE}),
        json.dumps({"x": [0, 0], "spp": "1_0"}),
        '{"x": [NaN, 0]}',
        json.dumps({"x": {"a": 1}}),
        json.dumps({"x": [True, False]}),
        json.dumps({"x": "chrome", "spp": [4]}),
        json.dumps({"x": "chrome", "basis": ["a"]}),
        json.dumps({"x": "chrome", "basis": {"a": 1}}),
        json.dumps([1, 2]),
        '"text"',
        "\xff\xfe",
        json.dumps({"x": ["1_0", "0"]}),
        json.dumps({"x": "١,٢"}),
    ],
)
def test_malformed_reference_bodies_answer_400(client, no_renders, body):
    _one_line_error(client.post("/api/reference", content=body.encode("utf-8", "surrogatepass")))
    assert not no_renders


@pytest.mark.parametrize(
    "url",
    [
        "/api/frame?x=1_0,0",
        "/api/frame?x=0,0&exposure=1_0",
        f"/api/frame?x={HUGE},0",
        f"/api/frame?x=0,0&exposure={HUGE}",
        "/api/frame?x=%D9%A1,%D9%A2",
        "/api/frame?x=0,0&format=gif",
        "/api/map?dims=0,1&extent=0,1,0,1_0",
        f"/api/map?dims={HUGE},0",
        "/api/map?dims=%D9%A1,0",
        f"/api/path?a=chrome&b=0,0&steps={HUGE}",
        "/api/path?a=chrome&b=0,0&steps=1_0",
        "/api/snippet?x=inf,0",
        "/api/material?x=0x10,0",
        "/api/table?x=%2B-1,0",
    ],
)
def test_malformed_queries_answer_400(client, url):
    _one_line_error(client.get(url))


def test_strict_numbers(explorer):
    for bad in ("1_0,0", "0x1,0", "1e5000,0", " ,", "١,٢", "1..2,0"):
        with pytest.raises(InputError):
            explorer.point(bad)
    for bad in ("1_0", HUGE, True, [1], {"a": 1}, "nan", float("inf")):
        with pytest.raises(InputError):
            explorer.number(bad, "exposure", -20, 20, 0.0)
    np.testing.assert_array_equal(explorer.point("1e-3, -2.5E+1"), [1e-3, -25.0])
    assert explorer.number("-1.5", "exposure", -20, 20, 0.0) == -1.5


JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-HUGE, max_value=HUGE)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=20)
    | st.sampled_from(
        ["chrome", "1_0,0", "0,0", "0.1,-0.2", "nan,0", "", "0", "frame", "basis_sphere"]
    ),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)
QUERY = st.one_of(
    st.text(max_size=30),
    st.integers(min_value=-HUGE, max_value=HUGE).map(str),
    st.sampled_from(
        [
            "chrome",
            "0,0",
            "0.1,0.2",
            "1_0,0",
            "nan,0",
            "0,1",
            "0,0,0,0",
            "0,1,0,1",
            "png",
            "rgba",
            "jpeg",
            "..%2F..",
            "-1e309,0",
        ]
    ),
)
ROUTES = [
    "/api/frame",
    "/api/material",
    "/api/table",
    "/api/map",
    "/api/snippet",
    "/api/path",
    "/api/info",
    "/api/reference/r1",
    "/api/reference/r1/blend.png",
    "/api/route",
    "/api/thumbs.png",
]


@SUITE
@given(
    route=st.sampled_from(ROUTES),
    params=st.dictionaries(
        st.sampled_from(
            ["x", "exposure", "format", "basis", "dims", "extent", "a", "b", "steps", "kind"]
        ),
        QUERY,
        max_size=5,
    ),
)
def test_fuzz_http_queries(client, route, params):
    r = client.get(route, params=params)
    if r.status_code != 200:
        _one_line_error(r, (400, 404))


@SUITE
@given(body=JSON | st.text(max_size=40).map(lambda t: {"raw": t}))
def test_fuzz_http_reference_bodies(client, no_renders, body):
    raw = (
        body["raw"].encode("utf-8", "surrogatepass")
        if isinstance(body, dict) and "raw" in body
        else json.dumps(body).encode()
    )
    r = client.post("/api/reference", content=raw, headers={"content-type": "application/json"})
    if r.status_code == 200:
        assert r.json()["state"] == "queued" and no_renders
    else:
        _one_line_error(r)


# ---------------------------------------------------------------- websocket input


def _closed_with(client, send, code):
    with pytest.raises(WebSocketDisconnect) as closed:
        with _ws(client) as ws:
            send(ws)
            while True:
                ws.receive_bytes()
    assert closed.value.code == code and closed.value.reason, (
        closed.value.code,
        closed.value.reason,
    )
    return closed.value.reason


def test_websocket_closes_on_binary_and_oversized_messages(client):
    assert "binary" in _closed_with(client, lambda ws: ws.send_bytes(b"\x00\x01"), 1003)
    big = json.dumps({"type": "frame", "x": "chrome", "pad": "a" * MAX_MESSAGE})
    assert "at most" in _closed_with(client, lambda ws: ws.send_text(big), 1009)
    assert "at most" in _closed_with(
        client, lambda ws: ws.send_text("[" * 100000 + "]" * 100000), 1009
    )


@pytest.mark.parametrize(
    "message",
    [
        "[" * 30000 + "]" * 30000,
        json.dumps({"type": "frame", "seq": 1, "x": [HUGE, 0]}),
        json.dumps({"type": "frame", "seq": 1, "x": "chrome", "exposure": HUGE}),
        json.dumps({"type": "frame", "seq": HUGE, "x": "chrome"}),
        json.dumps({"type": "frame", "seq": True, "x": "chrome"}),
        json.dumps({"type": ["frame"], "x": "chrome"}),
        json.dumps({"type": "move", "want": "frame", "x": "chrome"}),
        json.dumps({"type": "move", "want": [["frame"]], "x": "chrome"}),
        json.dumps({"type": "map", "x": "chrome", "dims": [1e400, 0]}),
        '{"type": "frame", "x": [NaN, 0]}',
        json.dumps({"type": "frame", "x": "chrome", "format": {"a": 1}}),
        json.dumps({"type": "frame", "x": "chrome", "basis": [1]}),
        json.dumps({"type": "path", "a": "chrome", "b": [0, 0], "steps": HUGE}),
        json.dumps({"type": "table", "x": ["1_0", 0]}),
        json.dumps({"type": "map", "x": "chrome", "extent": {"a": 1}}),
        json.dumps({"type": "route", "a": "chrome", "b": "chrome"}),
        json.dumps({"type": "route", "a": "chrome", "b": "steel", "kind": ["geodesic"]}),
        json.dumps({"type": "route", "a": "chrome", "b": "steel", "steps": HUGE}),
        json.dumps({"type": "route", "a": [1e400]}),
        "null",
        "[]",
        '"frame"',
        "garbage",
    ],
)
def test_malformed_websocket_messages_answer_an_error_and_the_tab_stays(client, message):
    with _ws(client) as ws:
        ws.send_text(message)
        meta, _ = _unpack(ws.receive_bytes())
        assert (
            meta["type"] == "error"
            and "\n" not in meta["error"]
            and "Traceback" not in meta["error"]
        ), meta
        ws.send_text(json.dumps({"type": "snippet", "seq": 7, "x": "chrome"}))  # still answering
        meta, _ = _unpack(ws.receive_bytes())
        assert meta["type"] == "snippet" and meta["seq"] == 7


def test_parse_never_raises_anything_else():
    @settings(max_examples=400, deadline=None)
    @given(st.one_of(JSON.map(json.dumps), st.text(max_size=60)))
    def check(text):
        try:
            out = parse(text)
        except (InputError, Closing):
            return
        assert out and all(isinstance(k, str) and isinstance(r, dict) for k, r in out)

    check()


def test_service_inputs_never_raise_anything_else(explorer):
    calls = [
        lambda v: explorer.point(v),
        lambda v: explorer.number(v, "exposure", -20, 20, 0.0),
        lambda v: explorer.map_png(v, [0.0, 0.0]),
        lambda v: explorer.map_png("0,1", [0.0, 0.0], v),
        lambda v: explorer.key(v),
        lambda v: explorer.frame(None, [0.0, 0.0], 0.0, v),
        lambda v: explorer.path_command(None, "chrome", v, None),
        lambda v: explorer.path_command(None, "chrome", "0,0", v),
        lambda v: explorer.path_command(None, "chrome", "steel", 5, v),
        lambda v: explorer.route("chrome", v, 5, "straight"),
        lambda v: explorer.route("chrome", "steel", v, "straight"),
        lambda v: (
            explorer.route("chrome", "steel", 5, v)
            if v not in ("uniform", "geodesic", None, "")
            else None
        ),
    ]

    @settings(max_examples=300, deadline=None)
    @given(st.integers(0, len(calls) - 1), JSON | QUERY)
    def check(which, value):
        try:
            calls[which](value)
        except InputError as e:
            assert "\n" not in str(e) and len(str(e)) < 400, str(e)

    check()


@SUITE
@given(
    messages=st.lists(
        st.one_of(
            JSON.map(json.dumps),
            st.fixed_dictionaries(
                {
                    "type": st.sampled_from(
                        ["frame", "table", "material", "snippet", "map", "path", "route", "move"]
                    ),
                    "seq": st.integers(0, 100),
                },
                optional={
                    "x": JSON,
                    "exposure": JSON,
                    "format": JSON,
                    "basis": JSON,
                    "want": JSON,
                    "dims": JSON,
                    "extent": JSON,
                    "a": JSON,
                    "b": JSON,
                    "steps": JSON,
                    "kind": st.sampled_from(["straight", "uniform", "geodesic"]) | JSON,
                },
            ).map(json.dumps),
        ),
        min_size=1,
        max_size=4,
    )
)
def test_fuzz_websocket(client, messages):
    """Random messages, then a sentinel: every answer until the sentinel's is well formed."""
    with _ws(client) as ws:
        for m in messages:
            ws.send_text(m)
        ws.send_text(json.dumps({"type": "path", "seq": 10**6, "a": "chrome", "b": "steel"}))
        while True:
            meta, payload = _unpack(ws.receive_bytes())
            assert meta["type"] in (
                "frame",
                "table",
                "material",
                "snippet",
                "map",
                "path",
                "route",
                "error",
            ), meta
            if meta["type"] == "error":
                assert "\n" not in meta["error"] and "internal error" not in meta["error"], meta
            if meta.get("seq") == 10**6 and meta["type"] == "path":
                break
