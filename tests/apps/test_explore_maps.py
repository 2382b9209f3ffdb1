"""The explorer's latent maps next to a drag: made a few rows at a time after the frames being
made, once for two requests of the same map, and abandoned when a newer map is asked for."""

import threading
import time

import numpy as np
import pytest

pytest.importorskip("mitsuba")
pytest.importorskip("starlette")
pytestmark = pytest.mark.render

import test_explore  # noqa: E402

from mitsuba_manifold.apps.explore import latentmap, service  # noqa: E402
from mitsuba_manifold.apps.explore.web.session import Session, Superseded  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402

small_basis, explorer = test_explore.small_basis, test_explore.explorer


def test_a_map_made_in_chunks_is_the_map_made_at_once(small_manifold_paper, monkeypatch):
    m = Manifold.load(small_manifold_paper)
    whole = latentmap.render(m, m.latent[1], (0, 1), resolution=40)
    calls = []
    monkeypatch.setattr(latentmap, "CHUNK", 7)  # 40 * 40 points: 229 chunks, the last one short
    chunked = latentmap.render(m, m.latent[1], (0, 1), resolution=40, pause=lambda: calls.append(1))
    np.testing.assert_array_equal(chunked.image, whole.image)
    assert len(calls) == -(-40 * 40 // 7) and chunked.info() == whole.info()


def _counting(monkeypatch, bounds):
    """Chunks computed of the maps zoomed on ``bounds`` (latentmap's albedo of a chunk), counted:
    those of other maps (the explorer's first one) left out."""
    done, albedo = [], latentmap._albedo
    lo, hi = (float(v) for v in bounds.split(",")[:2])

    def counted(manifold, pts):
        if lo - 1e-9 <= pts[:, 0].min() and pts[:, 0].max() <= hi + 1e-9:
            done.append(len(pts))
        return albedo(manifold, pts)

    monkeypatch.setattr(latentmap, "_albedo", counted)
    return done


def test_a_map_waits_while_a_frame_is_made(explorer, small_manifold_paper, monkeypatch):
    """No row of a map is computed while a frame is being made (up to FRAME_WAIT per chunk)."""
    monkeypatch.setattr(service, "FRAME_WAIT", 60.0)
    zoom = "0.11,0.12,0.11,0.12"
    done = _counting(monkeypatch, zoom)
    m = Manifold.load(small_manifold_paper)
    got = []
    with explorer._framing:  # a frame being made
        t = threading.Thread(
            target=lambda: got.append(explorer.map_png("0,1", m.latent[2], zoom, coarse=True))
        )
        t.start()
        time.sleep(0.5)
        assert not done and not got
    t.join(60)
    assert got and sum(done) == service.COARSE_MAP**2


def test_a_map_waits_while_a_drags_frames_keep_coming(explorer, small_manifold_paper, monkeypatch):
    """Between two frames of a drag (closer than DRAG_QUIET) no row of a map is computed; once
    the frames pause, the map is made."""
    monkeypatch.setattr(service, "FRAME_WAIT", 60.0)
    monkeypatch.setattr(service, "DRAG_QUIET", 2.0)  # frames 50 ms apart, even on a busy machine
    zoom = "0.41,0.42,0.41,0.42"
    done = _counting(monkeypatch, zoom)
    m = Manifold.load(small_manifold_paper)
    got = []
    t = threading.Thread(
        target=lambda: got.append(explorer.map_png("0,1", m.latent[2], zoom, coarse=True))
    )
    with explorer._framing:
        t.start()
    for _ in range(20):  # a drag: a frame every 50 ms for a second
        time.sleep(0.05)
        with explorer._framing:
            pass
    assert not done and not got
    t.join(60)
    assert got and sum(done) == service.COARSE_MAP**2


def test_a_map_asked_twice_at_once_is_made_once(explorer, small_manifold_paper, monkeypatch):
    made, render = [], latentmap.render

    def slow(*args, **kwargs):
        if kwargs.get("bounds") == (0.21, 0.22, 0.21, 0.22):  # not the explorer's first maps
            made.append(1)
            time.sleep(0.3)  # the second request arrives while this one is being made
        return render(*args, **kwargs)

    monkeypatch.setattr(latentmap, "render", slow)
    x = Manifold.load(small_manifold_paper).latent[3]
    got = []
    threads = [
        threading.Thread(
            target=lambda: got.append(explorer.map_png("0,1", x, "0.21,0.22,0.21,0.22", True))
        )
        for _ in range(2)
    ]
    for t in threads:
        t.start()
        time.sleep(0.05)
    for t in threads:
        t.join(60)
    assert len(made) == 1 and len(got) == 2 and got[0] is got[1]


def test_a_map_nobody_wants_is_abandoned(explorer, small_manifold_paper, monkeypatch):
    """The session's check raises once a newer map waits: the map stops within a chunk, is not
    kept, and the next request for it makes it in full."""
    zoom = "0.31,0.32,0.31,0.32"
    done = _counting(monkeypatch, zoom)
    x = Manifold.load(small_manifold_paper).latent[4]
    calls = []

    def stale():
        calls.append(1)
        if len(calls) > 2:
            raise Superseded()

    with pytest.raises(Superseded):
        explorer.map_png("0,1", x, zoom, stale=stale)
    assert len(done) == 2 and sum(done) < service.FULL_MAP**2
    png, meta = explorer.map_png("0,1", x, zoom)
    assert sum(done) == 2 * latentmap.CHUNK + service.FULL_MAP**2 and png[:4] == b"\x89PNG"


def test_the_session_abandons_its_map_when_a_newer_one_waits():
    session = Session.__new__(Session)
    session.pending = {"frame": {"seq": 3}}
    session.stale_map()  # a frame waiting: the map goes on
    session.pending["map"] = {"seq": 4}
    with pytest.raises(Superseded):
        session.stale_map()


def test_a_request_for_the_same_map_lets_the_map_being_made_go_on(explorer, small_manifold_paper):
    """The page asks again for the map it is waiting for (all parts asked anew once the tables
    are ready): the map being made goes on; a request for another slice or zoom stops it."""
    x = Manifold.load(small_manifold_paper).latent[4]
    session = Session.__new__(Session)
    session.ex = explorer
    key = explorer.map_key([0, 1], x, "0.31,0.32,0.31,0.32", False)
    session.pending = {
        "map": {
            "seq": 5,
            "x": [float(v) for v in x],
            "dims": [0, 1],
            "extent": "0.31,0.32,0.31,0.32",
        }
    }
    session.stale_map(key)  # the same map: goes on
    session.pending["map"]["extent"] = "0.41,0.42,0.41,0.42"
    with pytest.raises(Superseded):
        session.stale_map(key)
    session.pending["map"]["x"] = "not a point"
    with pytest.raises(Superseded):
        session.stale_map(key)
