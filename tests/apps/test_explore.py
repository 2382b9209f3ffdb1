"""tools/explore.py: the service, the HTTP/websocket API and the page in a real (headless) Chromium.

A small basis of scenes/sphere.xml (all materials of the small manifold, 32x32, one pass)
is rendered once per module. The browser tests drive the system Chromium with Playwright
and skip only when Chromium or Playwright is absent (tools/setup.sh installs both).
"""

import json
import os
import struct
import time

import numpy as np
import pytest

mi = pytest.importorskip("mitsuba")
pytest.importorskip("starlette")
mi.set_variant("llvm_ad_rgb")
pytestmark = pytest.mark.render

import mitsuba_manifold  # noqa: E402
from mitsuba_manifold.apps.explore import Explorer, InputError, create_app
from mitsuba_manifold.apps.explore.web import launch  # noqa: E402
from mitsuba_manifold.basis.blend import blend  # noqa: E402
from mitsuba_manifold.basis.folder import Basis  # noqa: E402
from mitsuba_manifold.imaging import io as imageio
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402
from mitsuba_manifold.render.jobs.render_basis import render_basis  # noqa: E402
from mitsuba_manifold.render.scene import scenes

SPHERE = scenes.scene_path("sphere")
RES = 32


@pytest.fixture(scope="module")
def small_basis(small_manifold_paper, tmp_path_factory):
    mi.set_variant("llvm_ad_rgb")
    mitsuba_manifold.register()
    out = str(tmp_path_factory.mktemp("explore") / "basis_sphere")
    render_basis(SPHERE, small_manifold_paper, out, spp=4, resolution=RES, mode="onepass")
    return out


@pytest.fixture(scope="module")
def explorer(small_basis, small_manifold_paper):
    ex = Explorer([small_basis], manifold=small_manifold_paper)
    assert ex.tables.wait(120) == "ready", ex.tables.message
    yield ex
    ex.close()


#: What the test client's requests are allowed as (its Host is "testserver").
TEST_ORIGIN = "http://testserver"


def app_for(explorer):
    """The app of ``explorer`` answering the test client (Host ``testserver``) as the CLI
    answers ``--allow-origin http://testserver``."""
    from mitsuba_manifold.apps.explore.web.guard import AllowList

    return create_app(explorer, AllowList.for_server("127.0.0.1", 8765, [TEST_ORIGIN]))


@pytest.fixture(scope="module")
def client(explorer):
    from starlette.testclient import TestClient

    with TestClient(app_for(explorer)) as c:
        yield c


def _unpack(msg):
    n = struct.unpack("<I", msg[:4])[0]
    return json.loads(msg[4 : 4 + n]), msg[4 + n :]


def _expected_frame(explorer, x, exposure=0.0):
    img, _ = blend(
        Basis.load(explorer.bases[next(iter(explorer.bases))].folder),
        explorer.manifold_path,
        x=x,
        prune=explorer.prune,
    )
    return imageio.tonemap(img, exposure)


# ---------------------------------------------------------------- service


def test_frame_is_the_blend_of_the_point(explorer, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    for x in (m.latent[2], 0.5 * (m.latent[0] + m.latent[3])):
        data, meta = explorer.frame(None, x, 0.0, "rgba")
        got = np.frombuffer(data, np.uint8).reshape(RES, RES, 4)[..., :3]
        np.testing.assert_array_equal(got, _expected_frame(explorer, x))
        assert meta["width"] == meta["height"] == RES and meta["total_ms"] > 0


def test_material_description(explorer, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    i = m.index("gold-paint")
    info = explorer.material(m.latent[i])
    assert info["weights"][0] == {"name": "gold-paint", "w": 1.0, "kept": True}
    assert [w["kept"] for w in info["weights"]].count(True) == info["n_kept"] == 1
    assert (
        info["pruning"].startswith("1 of ")
        and info["pruning_albedo"] <= info["pruning_albedo_budget"]
    )
    assert info["nearest"][0]["name"] == "gold-paint" and info["nearest"][0]["distance"] == 0
    assert info["variance"] < 1e-3
    np.testing.assert_allclose(info["albedo"], m.albedos[i], rtol=1e-9)
    far = explorer.material(m.latent.mean(axis=0) + 50.0)
    assert far["variance"] == pytest.approx(1.0 + m.noise, rel=1e-6)


def test_tables_match_the_manifold(explorer, small_manifold_paper):
    """At 32x32x64 bins the preview keeps every bin: negative fraction and slice are exact."""
    m = Manifold.load(small_manifold_paper)
    # a point between materials where the affine weights make some bins negative
    pairs = [
        (i, j, t) for i in range(m.n) for j in range(m.n) if i != j for t in (0.3, 0.5, -0.4, 1.6)
    ]
    x = next(
        x
        for x in ((1 - t) * m.latent[i] + t * m.latent[j] for i, j, t in pairs)
        if m.negative_fraction(x, prune=explorer.prune) > 0
    )
    data, layout = explorer.preview_table(x)
    assert layout["dims"] == layout["full_dims"] == [32, 32, 64] and layout["strides"] == [1, 1, 1]
    table, _, _ = m.interpolate(x, prune=explorer.prune)
    half = np.frombuffer(data, np.float16).reshape(table.shape).astype(np.float32)
    np.testing.assert_allclose(half, np.clip(table, -65504, 65504), rtol=2e-3, atol=1e-6)
    info = explorer.material(x)
    assert info["negative_fraction"] == pytest.approx(
        m.negative_fraction(x, prune=explorer.prune), abs=1e-6
    )
    assert info["negative_fraction"] > 0
    np.testing.assert_allclose(
        explorer.tables.slice(x, explorer.prune), table[:, :, :, 32], rtol=1e-4, atol=1e-6
    )
    assert info["slice"]["png"].startswith("data:image/png;base64,")


def test_preview_tables_are_cached_beside_the_basis(
    explorer, small_basis, small_manifold_paper, tmp_path
):
    """The reduced tables are written once beside the basis, named by the tables' hashes; the
    next start reads that file and opens no table (here: a database folder that does not exist)."""
    from mitsuba_manifold.apps.explore.material import TableStack

    path = explorer.tables.cache_path()
    assert os.path.dirname(path) == os.path.join(small_basis, ".manifold-cache") and os.path.isfile(
        path
    )
    m = Manifold.load(small_manifold_paper)
    again = TableStack(m, database=str(tmp_path / "nowhere"), cache_dir=os.path.dirname(path))
    assert again.wait(30) == "ready" and "(cached)" in again.message, again.message
    x = 0.3 * m.latent[0] + 0.7 * m.latent[4]
    for a, b in zip(again.preview(x, explorer.prune), explorer.tables.preview(x, explorer.prune)):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(
        again.slice(x, explorer.prune), explorer.tables.slice(x, explorer.prune)
    )
    other = m.hashes[:]
    m.hashes = other[
        ::-1
    ]  # other tables: another cache file, so the database is read (and missing)
    assert (
        TableStack(m, database=str(tmp_path / "nowhere"), cache_dir=os.path.dirname(path)).wait(30)
        == "unavailable"
    )


def test_bad_points_are_refused(explorer):
    q = explorer.manifold.q
    for value, words in [
        ("nan,1", "NaN"),
        ([1.0, float("inf")], "NaN or Inf"),
        ("1,2,3", f"give {q}"),
        ("no-such-material", "unknown material"),
        (None, "numbers"),
        ("", "give"),
    ]:
        with pytest.raises(InputError, match=words):
            explorer.point(value)
    with pytest.raises(InputError, match="unknown basis"):
        explorer.frame("../../etc", [0.0] * q)
    with pytest.raises(InputError, match="format"):
        explorer.frame(None, [0.0] * q, 0.0, "gif")
    assert np.array_equal(
        explorer.point("chrome"), explorer.manifold.latent[explorer.manifold.index("chrome")]
    )


def test_several_bases_get_a_name_each(small_basis, small_manifold_paper):
    ex = Explorer([small_basis, small_basis], manifold=small_manifold_paper, load_tables=False)
    try:
        names = [b["name"] for b in ex.info()["bases"]]
        assert names == ["basis_sphere", "basis_sphere-2"]
        x = ex.manifold.latent[0]
        assert ex.frame(names[1], x, 0.0, "rgba")[0] == ex.frame(names[0], x, 0.0, "rgba")[0]
        assert ex.material(x)["tables"] == "unavailable"
        with pytest.raises(InputError, match="not loaded"):
            ex.preview_table(x)
    finally:
        ex.close()


def test_reference_scene_is_found_when_the_basis_moved(small_basis, small_manifold_paper, tmp_path):
    """A manifest naming a scene file that is gone: the shipped scene of that name and hash is
    used; --scene gives one explicitly (checked by hash); otherwise renders are refused."""
    import json as _json
    import shutil

    from mitsuba_manifold.errors import MismatchError

    moved = str(tmp_path / "moved")
    shutil.copytree(small_basis, moved)
    path = os.path.join(moved, "manifest.json")
    manifest = _json.load(open(path))
    manifest["scene"] = str(tmp_path / "gone" / "sphere.xml")
    open(path, "w").write(_json.dumps(manifest))
    ex = Explorer([moved], manifold=small_manifold_paper, load_tables=False)
    assert ex.scenes["moved"] == SPHERE and ex.info()["bases"][0]["scene_available"]
    ex.close()
    manifest["scene"] = str(tmp_path / "gone" / "elsewhere.xml")
    open(path, "w").write(_json.dumps(manifest))
    ex = Explorer([moved], manifold=small_manifold_paper, load_tables=False)
    assert ex.scenes["moved"] is None and not ex.info()["bases"][0]["scene_available"]
    with pytest.raises(
        InputError,
        match="missing or has changed since the basis was rendered; give it with --scene",
    ):
        ex.start_reference(None, ex.manifold.latent[0], 4)
    from starlette.testclient import TestClient

    with TestClient(app_for(ex)) as c:
        assert c.post("/api/reference", json={"x": "chrome"}).status_code == 400
    ex.close()
    ex = Explorer([moved], manifold=small_manifold_paper, load_tables=False, scene="sphere")
    assert ex.scenes["moved"] == SPHERE
    ex.close()
    with pytest.raises(MismatchError, match="another scene"):
        Explorer([moved], manifold=small_manifold_paper, load_tables=False, scene="table")


def test_reference_render_in_the_background(explorer, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    job = explorer.start_reference(None, m.latent[1], 4)
    deadline = time.monotonic() + 180
    while job.state in ("queued", "rendering") and time.monotonic() < deadline:
        time.sleep(0.1)
    assert job.state == "done", job.message
    assert job.progress == 1.0 and set(job.images) == {"blend", "reference"}
    assert np.isfinite(job.images["reference"]).all() and job.images["reference"].mean() > 0
    assert job.error["rel_mse"] >= 0 and np.isfinite(job.error["psnr"])
    # two passes at least, so the reference's own noise is known and the blend judged against it
    noise = job.error["noise_rel_mse"]
    assert noise > 0 and job.error["agrees"] == (job.error["rel_mse"] <= 2 * noise)
    assert job.error["excess_rel_mse"] == pytest.approx(max(job.error["rel_mse"] - noise, 0.0))
    png = explorer.reference_image(job.id, "error")
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(InputError, match="image must be"):
        explorer.reference_image(job.id, "../../secret")


# ---------------------------------------------------------------- HTTP


def test_http_bad_requests_get_400_with_a_message(client):
    for url, words in [
        ("/api/frame?x=nan,0", "NaN"),
        ("/api/frame?x=1,2,3", "give 2"),
        ("/api/frame?x=unobtainium", "unknown material"),
        ("/api/frame?x=0,0&basis=..%2F..", "unknown basis"),
        ("/api/frame?x=0,0&exposure=inf", "exposure"),
        ("/api/map?dims=0,0", "dims"),
        ("/api/map?extent=1,0,0,1", "extent"),
        ("/api/map?extent=0,1,0,nan", "extent"),
        ("/api/path?a=chrome&b=nan,1", "NaN"),
        ("/api/path?a=chrome&b=chrome", "same point"),
        ("/api/reference/r999", "unknown reference"),
        ("/api/reference/r1%20x/blend.png", "unknown reference"),
        ("/api/reference/r999/blend.png", "unknown reference"),
    ]:
        r = client.get(url)
        assert r.status_code == 400, (url, r.status_code, r.text)
        assert words in r.json()["error"], (url, r.json())
    r = client.post("/api/reference", content=b"not json")
    assert r.status_code == 400 and "JSON" in r.json()["error"]


def test_internal_errors_answer_500_without_a_traceback(explorer, monkeypatch):
    from starlette.testclient import TestClient

    def broken(*args, **kwargs):
        raise RuntimeError("secret detail /etc/passwd")

    monkeypatch.setattr(explorer, "material", broken)
    with TestClient(app_for(explorer), raise_server_exceptions=False) as c:
        r = c.get("/api/material", params={"x": "chrome"})
    assert r.status_code == 500 and r.json() == {
        "error": "internal error (RuntimeError); see the server's console"
    }


def test_static_files_stay_inside_their_folder(client):
    assert client.get("/static/app.js").status_code == 200
    for url in (
        "/static/../service.py",
        "/static/%2e%2e/service.py",
        "/static/..%2f__init__.py",
        "/static/%2e%2e/%2e%2e/manifold.py",
        "/api/reference/..%2F..%2Fetc/blend.png",
    ):
        r = client.get(url)
        assert r.status_code == 404 and b"import" not in r.content, url
    r = client.get("/nowhere")
    assert r.status_code == 404 and "error" in r.json()


def test_map_zooms_with_one_colour_scale(client):
    whole = client.get("/api/map").json()
    x0, x1, y0, y1 = whole["extent"]
    zoom = [x0, (x0 + x1) / 2, y0, (y0 + y1) / 2]
    part = client.get("/api/map", params={"extent": ",".join(map(str, zoom))}).json()
    assert part["extent"] == zoom and part["albedo_range"] == whole["albedo_range"]
    assert part["png"] != whole["png"] and part["png"].startswith("data:image/png;base64,")


def test_http_frame_and_snippet(client, explorer, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    x = m.latent[3]
    r = client.get("/api/frame", params={"x": ",".join(str(float(v)) for v in x), "format": "png"})
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    assert json.loads(r.headers["x-frame"])["width"] == RES
    s = client.get("/api/snippet", params={"x": "chrome"}).json()
    rel = os.path.relpath(explorer.manifold_path, explorer.snippet_folder())
    assert 'type="manifold_brdf"' in s["xml"] and f'name="manifold" value="{rel}"' in s["xml"]
    assert not rel.startswith("/") and 'value="$manifold"' in s["xml"]
    cmd = client.get("/api/path", params={"a": "chrome", "b": "0.1,0.2", "steps": 5}).json()[
        "command"
    ]
    assert "--path chrome 0.1,0.2 --steps 5" in cmd


def test_websocket_answers_the_newest_request_per_tab(client, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    with client.websocket_connect("/ws") as a, client.websocket_connect("/ws") as b:
        for seq in range(1, 6):
            a.send_text(
                json.dumps(
                    {"type": "frame", "seq": seq, "x": list(m.latent[seq % m.n]), "format": "rgba"}
                )
            )
        b.send_text(
            json.dumps({"type": "frame", "seq": 1, "x": list(m.latent[0]), "format": "jpeg"})
        )
        meta_b, payload_b = _unpack(b.receive_bytes())
        assert meta_b["seq"] == 1 and meta_b["format"] == "jpeg" and payload_b[:2] == b"\xff\xd8"
        seen = []
        while not seen or seen[-1] != 5:
            meta, payload = _unpack(a.receive_bytes())
            assert meta["type"] == "frame" and len(payload) == RES * RES * 4
            seen.append(meta["seq"])
        assert (
            seen == sorted(seen) and len(seen) <= 5
        )  # stale requests may be dropped, never reordered
        a.send_text(json.dumps({"type": "frame", "seq": 9, "x": [float("nan"), 0.0]}))
        meta, _ = _unpack(a.receive_bytes())
        assert meta["type"] == "error" and meta["seq"] == 9 and "NaN" in meta["error"]
        a.send_text("garbage")
        meta, _ = _unpack(a.receive_bytes())
        assert meta["type"] == "error" and "bad message" in meta["error"]


def test_other_sites_cannot_drive_the_server(client):
    from starlette.websockets import WebSocketDisconnect

    with pytest.raises(WebSocketDisconnect):
        with client.websocket_connect("/ws", headers={"origin": "http://evil.example"}) as ws:
            ws.receive_bytes()
    r = client.post("/api/reference", json={"x": [0, 0]}, headers={"origin": "http://evil.example"})
    assert r.status_code == 403
    with client.websocket_connect("/ws", headers={"origin": "http://testserver"}) as ws:
        ws.send_text(json.dumps({"type": "material", "seq": 1, "x": [0.0, 0.0]}))
        assert _unpack(ws.receive_bytes())[0]["type"] == "material"


# ---------------------------------------------------------------- CLI


def test_cli_refuses_a_missing_basis(tmp_path, capsys):
    from mitsuba_manifold.apps.cli.explore import main

    assert main(["--basis", str(tmp_path / "nothing"), "--port", "0"]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_cli_refuses_a_bad_prune(small_basis, capsys):
    from mitsuba_manifold.apps.cli.explore import main

    assert main(["--basis", small_basis, "--port", "0", "--prune", "1.5"]) == 2
    assert "prune must be in [0, 1)" in capsys.readouterr().err


def test_an_explicit_database_must_be_the_manifolds_tables(
    small_basis, small_manifold_paper, small_db, tmp_path, capsys
):
    from mitsuba_manifold.apps.cli.explore import main

    (tmp_path / "empty").mkdir()
    (tmp_path / "file.binary").write_bytes(b"x")
    for bad, why in (
        ("nowhere", "does not exist"),
        ("file.binary", "is a file"),
        ("empty", "is not a database folder of this manifold: it holds no table for 8 of its 8"),
    ):
        with pytest.raises(InputError, match=f"^--database {tmp_path / bad} {why}"):
            Explorer(
                [small_basis],
                manifold=small_manifold_paper,
                database=str(tmp_path / bad),
                load_tables=False,
            )
    assert (
        main(["--basis", small_basis, "--port", "0", "--database", str(tmp_path / "nowhere")]) == 2
    )
    err = capsys.readouterr().err
    assert (
        err.startswith(f"error: --database {tmp_path / 'nowhere'} does not exist")
        and err.count("\n") == 1
    )
    ex = Explorer(
        [small_basis], manifold=small_manifold_paper, database=small_db, load_tables=False
    )  # the right one
    ex.close()


def test_cli_refuses_a_busy_port(small_basis, capsys):
    from mitsuba_manifold.apps.cli.explore import bind, main

    sock = bind("127.0.0.1", 0)
    try:
        assert main(["--basis", small_basis, "--port", str(sock.getsockname()[1])]) == 2
        assert "choose another --port" in capsys.readouterr().err
    finally:
        sock.close()


def test_ctrl_c_stops_the_server_with_a_tab_connected(small_basis, small_manifold_paper):
    """Also: the real server closes connections whose request never ends (serving.py's
    deadline, 408) and keeps the tab's websocket open past that deadline."""
    import socket

    from websockets.sync.client import connect

    proc, url = launch.start([small_basis], small_manifold_paper, ["--no-tables"])
    port = int(url.rstrip("/").rsplit(":", 1)[1])
    stalled = [socket.create_connection(("127.0.0.1", port), timeout=30) for _ in range(3)]
    try:
        for s in stalled:
            s.sendall(b"GET /api/info HTTP/1.1\r\nHost: 127.0.0.1\r\n")  # never finished
        with connect(url.replace("http://", "ws://") + "ws", max_size=None) as ws:
            ws.send(json.dumps({"type": "frame", "seq": 1, "x": "chrome", "format": "jpeg"}))
            assert _unpack(ws.recv())[0]["type"] == "frame"
            for s in stalled:  # closed by the server, saying why
                assert s.recv(100).startswith(b"HTTP/1.1 408")
            ws.send(json.dumps({"type": "frame", "seq": 2, "x": "chrome", "format": "jpeg"}))
            assert _unpack(ws.recv())[0]["seq"] == 2  # the websocket outlives the deadline
            code, out = launch.stop(proc)  # SIGINT, as Ctrl-C, while the websocket is open
    finally:
        for s in stalled:
            s.close()
        if proc.poll() is None:
            proc.kill()
    assert code == 0 and out.strip().endswith("explore: stopped"), (code, out)


def test_real_server_refuses_other_hosts_and_ctrl_c_stops_a_render_within_2s(
    small_basis, small_manifold_paper, tmp_path, monkeypatch
):
    """Against the real server (uvicorn): a DNS-rebinding Host gets 403 on HTTP and on the
    websocket handshake; Ctrl-C while a reference render runs stops the server within 2 s, and
    leaves no temporary folder of the render behind."""
    import glob
    import signal
    import socket
    import urllib.error
    import urllib.request

    monkeypatch.setenv("TMPDIR", str(tmp_path))  # the server's temporary folders
    proc, url = launch.start([small_basis], small_manifold_paper, ["--no-tables"])
    try:
        port = url.rstrip("/").rsplit(":", 1)[1]
        evil = urllib.request.Request(url + "api/info", headers={"Host": f"evil.example:{port}"})
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(evil, timeout=10)
        assert refused.value.code == 403 and "refused" in json.loads(refused.value.read())["error"]
        for host, status in ((f"evil.example:{port}", b"403"), (f"127.0.0.1:{port}", b"101")):
            with socket.create_connection(("127.0.0.1", int(port)), timeout=10) as sock:
                sock.sendall(
                    f"GET /ws HTTP/1.1\r\nHost: {host}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                    "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n\r\n".encode()
                )
                assert sock.recv(100).split()[1] == status, host
        post = urllib.request.Request(
            url + "api/reference",
            data=json.dumps({"x": "chrome", "spp": 16384}).encode(),
            headers={"Content-Type": "application/json"},
            method="POST",
        )
        job = json.loads(urllib.request.urlopen(post, timeout=30).read())
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # rendering, past its first pass (kernels compiled)
            status = json.loads(
                urllib.request.urlopen(url + f"api/reference/{job['id']}", timeout=10).read()
            )
            if status["progress"] > 0:
                break
            time.sleep(0.05)
        assert status["state"] == "rendering" and status["progress"] < 0.5, status
        proc.send_signal(signal.SIGINT)
        # a render of 16384 spp runs for minutes: ended within the timeout, it was stopped
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0 and "explore: stopped" in out, (proc.returncode, out)
    assert glob.glob(str(tmp_path / "explore-reference-*")) == []


# ---------------------------------------------------------------- browser

CHROMIUM = launch.find_chromium()
try:
    import playwright.sync_api  # noqa: F401

    HAVE_PLAYWRIGHT = True
except ImportError:
    HAVE_PLAYWRIGHT = False
browser_only = pytest.mark.skipif(
    CHROMIUM is None or not HAVE_PLAYWRIGHT,
    reason="needs the system Chromium and Playwright (tools/setup.sh installs both: apt chromium, pip playwright)",
)


@pytest.fixture(scope="module")
def server(small_basis, small_manifold_paper):
    proc, url = launch.start([small_basis], small_manifold_paper)
    yield url
    code, out = launch.stop(proc)
    assert code == 0 and "stopped" in out, (code, out)  # Ctrl-C stops it cleanly


@pytest.fixture(scope="module")
def page(server):
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(
            executable_path=CHROMIUM,
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
        )
        pg = browser.new_context(viewport={"width": 1500, "height": 1000}).new_page()
        errors = []
        pg.on("pageerror", lambda e: errors.append(str(e)))
        pg.goto(server)
        pg.wait_for_function(
            "window.explore && window.explore.state.displayed && window.explore.state.material && window.explore.state.map",
            timeout=60000,
        )
        pg.errors = errors
        yield pg
        browser.close()


def _displayed_pixels(pg):
    data = pg.evaluate("""() => { const c = document.getElementById('scene');
        return Array.from(c.getContext('2d').getImageData(0, 0, c.width, c.height).data); }""")
    return np.array(data, dtype=np.uint8).reshape(RES, RES, 4)[..., :3]


def _wait_displayed(pg, x, timeout=30000):
    pg.wait_for_function(
        """(x) => { const d = window.explore.state.displayed;
        return d && d.x.length === x.length && d.x.every((v, k) => v === x[k]) &&
               window.explore.channel.pending() === 0; }""",
        arg=[float(v) for v in x],
        timeout=timeout,
    )


def _map_position(pg, x):
    """Page coordinates of latent point x on the map."""
    return pg.evaluate(
        """(x) => { const s = window.explore.state, c = document.getElementById('map');
        const r = c.getBoundingClientRect(), [x0, x1, y0, y1] = s.map.extent;
        return [r.left + (x[s.dims[0]] - x0) / (x1 - x0) * r.width,
                r.top + (1 - (x[s.dims[1]] - y0) / (y1 - y0)) * r.height]; }""",
        [float(v) for v in x],
    )


def _click_material(page, manifold_path, name):
    """Click on a material's point on the map and wait for its frame; returns its latent point."""
    x = Manifold.load(manifold_path).latent[Manifold.load(manifold_path).index(name)]
    page.mouse.click(*_map_position(page, x))
    _wait_displayed(page, x)
    return x


@browser_only
def test_click_on_a_material_shows_its_blend(page, explorer, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    page.mouse.move(*_map_position(page, m.latent[m.index("gold-paint")]))
    page.wait_for_selector("#tooltip:not([hidden])")
    assert page.inner_text("#tooltip") == "gold-paint"  # names on hover
    x = _click_material(page, small_manifold_paper, "gold-paint")
    np.testing.assert_array_equal(_displayed_pixels(page), _expected_frame(explorer, x))
    page.wait_for_function("document.getElementById('material-name').textContent === 'gold-paint'")
    assert not page.errors


@browser_only
def test_drag_changes_the_image(page, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    start = _click_material(page, small_manifold_paper, "steel")
    before = _displayed_pixels(page)
    x0, y0 = _map_position(page, start)
    x1, y1 = _map_position(page, 0.5 * (start + m.latent[m.index("pink-fabric")]) + 0.05)
    page.mouse.move(x0, y0)
    page.mouse.down()
    for t in np.linspace(0, 1, 8)[1:]:
        page.mouse.move(x0 + t * (x1 - x0), y0 + t * (y1 - y0))
    page.mouse.up()
    page.wait_for_function(
        """(s) => { const d = window.explore.state.displayed;
        return d && (d.x[0] !== s[0] || d.x[1] !== s[1]) && window.explore.channel.pending() === 0; }""",
        arg=[float(v) for v in start],
    )
    assert np.abs(_displayed_pixels(page).astype(int) - before).mean() > 0.5
    assert not page.errors


@browser_only
def test_preview_sphere_is_shaded(page, small_manifold_paper):
    _click_material(page, small_manifold_paper, "white-diffuse-bball")
    page.wait_for_function(
        "() => { const p = window.explore.preview; return p.envReady && !p.fast && !p.pending; }"
    )  # drawn in full (its worker has answered)
    centre, corner = page.evaluate("""() => { const s = document.getElementById('sphere');
        const c = document.createElement('canvas'); c.width = s.width; c.height = s.height;
        const g = c.getContext('2d'); g.drawImage(s, 0, 0);
        const px = (x, y) => Array.from(g.getImageData(x, y, 1, 1).data);
        return [px(s.width * 0.62, s.height * 0.38), px(s.width * 0.25, s.height * 0.78)]; }""")
    assert page.evaluate("!!window.explore.preview.worker && window.explore.preview.draws > 0")
    # the side facing the key light (upper right) is lit, the one facing the ground (lower left) much less
    lit, away = centre, corner
    assert sum(lit[:3]) > 3 * 60 and sum(lit[:3]) > sum(away[:3]) + 60, (lit, away)


@browser_only
def test_xml_snippet_loads_in_mitsuba_and_renders(page, small_manifold_paper, tmp_path):
    m = Manifold.load(small_manifold_paper)
    x = 0.5 * (m.latent[m.index("blue-acrylic")] + m.latent[m.index("chrome")])
    page.evaluate("(x) => window.explore.setX(x)", [float(v) for v in x])
    _wait_displayed(page, x)
    page.fill(
        "#snippet-folder", str(tmp_path)
    )  # the scene's folder: the manifold is named relative to it
    page.dispatch_event("#snippet-folder", "change")
    rel = os.path.relpath(small_manifold_paper, tmp_path)
    page.wait_for_function(
        "(rel) => document.getElementById('snippet').textContent.includes(rel)",
        arg=rel,
        timeout=10000,
    )
    page.wait_for_function(
        "(x) => document.getElementById('snippet').textContent.includes(x)",
        arg=f"{x[0]:.6g}",
        timeout=10000,
    )
    xml = page.inner_text("#snippet")
    scene = f"""<scene version="3.0.0"><integrator type="path"/>{xml}
        <shape type="sphere"><ref id="material"/></shape>
        <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
        <sensor type="perspective"><transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/>
        </transform><film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler></sensor></scene>"""
    (tmp_path / "scene.xml").write_text(scene)
    mi.set_variant("llvm_ad_rgb")
    mitsuba_manifold.register()
    img = np.array(mi.render(mi.load_file(str(tmp_path / "scene.xml"))))
    assert np.isfinite(img).all() and img[6:10, 6:10].mean() > 0
    bsdf = [s.bsdf() for s in mi.load_file(str(tmp_path / "scene.xml")).shapes()][0]
    np.testing.assert_allclose(bsdf.latent, x, rtol=1e-5)


@browser_only
def test_bad_request_from_the_page_gets_400(page):
    r = page.evaluate("""async () => { const r = await fetch('/api/frame?x=NaN,0');
        return [r.status, (await r.json()).error]; }""")
    assert r[0] == 400 and "NaN" in r[1]
    r = page.evaluate("""async () => { const r = await fetch('/api/frame?x=0,0&basis=' + encodeURIComponent('../../etc'));
        return [r.status, (await r.json()).error]; }""")
    assert r[0] == 400 and "unknown basis" in r[1]


@browser_only
def test_link_restores_the_point_and_save_png_is_the_frame(
    page, server, explorer, small_manifold_paper
):
    import io

    from PIL import Image

    x = _click_material(page, small_manifold_paper, "chrome")
    page.wait_for_function(
        "(x) => location.hash.startsWith('#x=' + x.join(','))", arg=[float(v) for v in x]
    )
    link = page.url  # the address follows the point (at most every 200 ms)
    other = page.context.new_page()
    try:
        other.goto(link)
        _wait_displayed(other, x)
        href = other.get_attribute("#save-png", "href")
        png = other.evaluate(
            "async (u) => Array.from(new Uint8Array(await (await fetch(u)).arrayBuffer()))", href
        )
        saved = np.asarray(Image.open(io.BytesIO(bytes(png))).convert("RGB"))
        np.testing.assert_array_equal(saved, _displayed_pixels(other))
    finally:
        other.close()


@browser_only
def test_two_tabs_at_once(page, server, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    other = page.context.new_page()
    try:
        other.goto(server)
        other.wait_for_function(
            "window.explore && window.explore.state.displayed && window.explore.state.map",
            timeout=60000,
        )
        xa, xb = m.latent[m.index("chrome")], m.latent[m.index("pink-fabric")]
        page.evaluate("(x) => window.explore.setX(x)", [float(v) for v in xa])
        other.evaluate("(x) => window.explore.setX(x)", [float(v) for v in xb])
        _wait_displayed(page, xa)
        _wait_displayed(other, xb)
        assert not np.array_equal(_displayed_pixels(page), _displayed_pixels(other))
    finally:
        other.close()


@browser_only
def test_path_scrubber_and_export(page, small_manifold_paper):
    page.select_option("#path-kind", "straight")
    a = _click_material(page, small_manifold_paper, "chrome")
    page.click("#set-a")
    b = _click_material(page, small_manifold_paper, "pink-fabric")
    page.click("#set-b")
    page.fill("#scrub", "250")
    page.dispatch_event("#scrub", "input")
    x = np.array(page.evaluate("window.explore.state.x"))
    np.testing.assert_allclose(x, 0.75 * a + 0.25 * b, rtol=1e-12, atol=1e-12)
    _wait_displayed(page, x)
    page.fill("#steps", "7")
    page.click("#export-path")
    page.wait_for_selector("#path-cmd:not([hidden])")
    assert "--path chrome pink-fabric --steps 7 --path-kind straight" in page.inner_text(
        "#path-cmd"
    )


@browser_only
def test_without_webgl_the_page_says_so_and_works(page, server, explorer, small_manifold_paper):
    other = page.context.new_page()
    try:
        other.add_init_script("""{ const get = HTMLCanvasElement.prototype.getContext;
            HTMLCanvasElement.prototype.getContext = function (kind, ...rest) {
                return kind === 'webgl2' ? null : get.call(this, kind, ...rest); };
            delete HTMLCanvasElement.prototype.transferControlToOffscreen; }""")  # no WebGL for the sphere's worker
        other.goto(server)
        other.wait_for_function(
            "window.explore && window.explore.state.displayed && window.explore.state.map",
            timeout=60000,
        )
        assert "WebGL 2 is not available" in other.inner_text("#sphere-msg")
        x = _click_material(other, small_manifold_paper, "blue-acrylic")
        np.testing.assert_array_equal(_displayed_pixels(other), _expected_frame(explorer, x))
    finally:
        other.close()


def _shade_like_the_preview(table, strides, lights, size):
    """NumPy mirror of static/preview.js: MERL lookup (merl.half_diff, merl_bin's sqrt mapping),
    trilinear between texels, the page's lights (the environment's and the key light: [direction,
    RGB irradiance]), sRGB. Returns (size, size, 3) in [0, 1] and the sphere mask."""
    from mitsuba_manifold.data import merl

    n_h, n_d, n_p = table.shape[1:]
    full = np.array([n_h, n_d, n_p]) * np.array(strides)
    j, i = np.meshgrid(np.arange(size), np.arange(size))
    uv = np.stack([(j + 0.5) / size * 2 - 1, 1 - (i + 0.5) / size * 2], axis=-1) * 1.08
    r2 = (uv**2).sum(-1)
    inside = r2 < 0.98
    n = np.concatenate([uv, np.sqrt(np.maximum(1 - r2, 0))[..., None]], axis=-1)[inside]
    t = np.cross([0.0, 1.0, 0.0], n)
    t /= np.linalg.norm(t, axis=-1, keepdims=True)
    b = np.cross(n, t)
    local = lambda d: np.stack([(d * t).sum(-1), (d * b).sum(-1), (d * n).sum(-1)], axis=-1)  # noqa: E731
    wo = local(np.broadcast_to([0.0, 0.0, 1.0], n.shape))
    out = np.zeros(n.shape)
    for d, power in lights:
        d, power = (
            np.asarray(d, dtype=np.float64) / np.linalg.norm(d),
            np.asarray(power, dtype=np.float64),
        )
        wi = local(np.broadcast_to(d, n.shape))
        th, td, pd = merl.half_diff(wi, wo)
        pd = np.where(pd < 0, pd + np.pi, pd)
        c = np.stack(
            [
                np.sqrt(np.clip(th / (np.pi / 2), 0, 1)) * full[0],
                td / (np.pi / 2) * full[1],
                pd / np.pi * full[2],
            ],
            axis=-1,
        )
        r = np.clip((c - 0.5) / np.array(strides) + 0.5, 0.5, np.array([n_h, n_d, n_p]) - 0.5) - 0.5
        lo = np.minimum(np.floor(r).astype(int), np.array([n_h, n_d, n_p]) - 1)
        hi = np.minimum(lo + 1, np.array([n_h, n_d, n_p]) - 1)
        f = r - lo
        val = 0.0
        for corner in range(8):
            idx = [np.where(corner >> a & 1, hi[:, a], lo[:, a]) for a in range(3)]
            wgt = np.prod(
                [np.where(corner >> a & 1, f[:, a], 1 - f[:, a]) for a in range(3)], axis=0
            )
            val = val + wgt[:, None] * table[:, idx[0], idx[1], idx[2]].T
        ok = (wi[:, 2] > 0) & (wo[:, 2] > 0)
        out += np.where(ok[:, None], np.maximum(val, 0) * wi[:, 2:3] * power, 0.0)
    img = np.zeros((size, size, 3))
    img[inside] = imageio.srgb_encode(out)
    return img, inside


@browser_only
def test_preview_follows_the_merl_mapping(page, small_manifold_paper):
    """The sphere drawn by the fragment shader matches the same shading computed in NumPy from
    the interpolated table with merl.half_diff: wrong axes or bin mappings would not."""
    m = Manifold.load(small_manifold_paper)
    x = 0.6 * m.latent[m.index("gold-paint")] + 0.4 * m.latent[m.index("steel")]
    page.evaluate("(x) => window.explore.setX(x)", [float(v) for v in x])
    page.wait_for_function(
        "(x) => { const p = window.explore.state.previewX; return p && p.every((v, k) => v === x[k]); }",
        arg=[float(v) for v in x],
        timeout=30000,
    )
    page.wait_for_function("window.explore.preview.envReady && !window.explore.preview.fast")
    # an earlier test may have dragged the key light anywhere: put it where it starts, off both
    # axes, so that the sphere it lights is not the same flipped
    page.evaluate("window.explore.preview.key = [0.55, 0.6, 0.58]")
    page.select_option(
        "#lighting", "key"
    )  # the key light alone: one direction, shaded exactly in NumPy
    page.eval_on_selector(
        "#key-power", "e => { e.value = '1'; e.dispatchEvent(new Event('input')); }"
    )
    page.wait_for_function("window.explore.preview.keyPower > 0 && !window.explore.preview.pending")
    table = (
        np.clip(m.interpolate(x, prune=1e-3)[0], -65504, 65504)
        .astype(np.float16)
        .astype(np.float64)
    )
    read = """() => { const s = document.getElementById('sphere');
        const c = document.createElement('canvas'); c.width = s.width; c.height = s.height;
        const g = c.getContext('2d'); g.drawImage(s, 0, 0);
        return [s.width, Array.from(g.getImageData(0, 0, s.width, s.height).data), [window.explore.preview.keyLight()]]; }"""
    # the worker's frame reaches the page's canvas a little after its "drawn" answer: read the
    # canvas until it shows the expected sphere (or 20 s have passed), then judge the last read
    deadline = time.monotonic() + 20
    while True:
        size, pixels, lights = page.evaluate(read)
        shown = np.array(pixels, dtype=np.float64).reshape(size, size, 4)[..., :3] / 255
        expected, inside = _shade_like_the_preview(table, (1, 1, 1), lights, size)
        # judged where either the expected sphere or its flip is lit (a single key light leaves
        # most of the sphere dark, where a canvas not yet drawn would match too)
        lit = inside & ((expected.max(-1) > 0.01) | (expected[::-1].max(-1) > 0.01))
        lit_err = np.abs(shown - expected).sum(-1)[lit]
        close = np.median(lit_err) < 0.012 and np.percentile(lit_err, 95) < 0.06
        if close or time.monotonic() > deadline:
            break
        page.wait_for_timeout(250)
    page.select_option("#lighting", "studio")
    page.eval_on_selector(
        "#key-power", "e => { e.value = '0'; e.dispatchEvent(new Event('input')); }"
    )
    assert expected[inside].max() > 0.3  # a lit, non-trivial sphere
    assert close, (np.median(lit_err), np.percentile(lit_err, 95))
    # the test can tell a flipped image apart (errors summed over RGB: a saturated material
    # leaves two channels dark everywhere)
    rotated = np.abs(shown - expected[::-1]).sum(-1)[lit]
    assert np.median(np.abs(expected - expected[::-1]).sum(-1)[lit]) > 0.005  # a flip would show
    assert np.median(rotated) > 2 * np.median(np.abs(shown - expected).sum(-1)[lit]) + 0.005


@pytest.fixture(scope="module")
def q3_basis(small_db, tmp_path_factory):
    """A q = 3 manifold and a basis of the shipped sphere.xml (its default point suits any q)."""
    folder = tmp_path_factory.mktemp("explore_q3")
    manifold = str(folder / "manifold_q3.npz")
    Manifold.fit(small_db, q=3, max_iter=40).save(manifold)
    mi.set_variant("llvm_ad_rgb")
    mitsuba_manifold.register()
    out = str(folder / "basis_q3")
    render_basis(SPHERE, manifold, out, spp=2, resolution=16, mode="onepass")
    return out, manifold


@browser_only
def test_q3_map_is_a_slice_with_a_slider(page, q3_basis):
    basis, manifold = q3_basis
    proc, url = launch.start([basis], manifold, ["--no-tables"])
    other = page.context.new_page()
    try:
        other.goto(url)
        other.wait_for_function(
            "window.explore && window.explore.state.displayed && window.explore.state.map",
            timeout=60000,
        )
        assert other.is_visible("#slice-controls")
        assert other.eval_on_selector_all(
            "#sliders input", "els => els.map(e => +e.dataset.dim)"
        ) == [2]
        before = other.evaluate("window.explore.state.map.png")
        x = other.evaluate("window.explore.state.x")
        slider = other.locator("#sliders input")
        target = float(slider.get_attribute("min")) + 0.8 * (
            float(slider.get_attribute("max")) - float(slider.get_attribute("min"))
        )
        slider.fill(str(target))
        slider.dispatch_event("input")
        moved = other.evaluate("window.explore.state.x")
        assert moved[:2] == x[:2] and moved[2] == pytest.approx(
            target, abs=1e-2 * abs(target) + 1e-2
        )
        _wait_displayed(other, moved)
        other.wait_for_function(
            "(b) => window.explore.state.map.png !== b", arg=before, timeout=30000
        )
        other.select_option("#dim1", "2")  # map axes x0 x x2: the slider is now x1
        other.wait_for_function("window.explore.state.map.dims[1] === 2", timeout=30000)
        assert other.eval_on_selector_all(
            "#sliders input", "els => els.map(e => +e.dataset.dim)"
        ) == [1]
    finally:
        other.close()
        code, out = launch.stop(proc)
        assert code == 0, out[-3000:]
