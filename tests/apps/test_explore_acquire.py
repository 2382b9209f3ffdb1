"""The explorer's acquisition: a photo of a basis's scene uploaded to ``/api/acquire`` gives back
the material that made it (weights, place on the map or named combination, contact sheet); a bad
upload answers one line; a page of another site may not upload."""

import base64
import io
import time

import numpy as np
import pytest

pytest.importorskip("starlette")
pytest.importorskip("mitsuba")
pytestmark = pytest.mark.render

import test_explore  # noqa: E402
from starlette.testclient import TestClient  # noqa: E402

from mitsuba_manifold.apps.explore import acquire as explore_acquire  # noqa: E402
from mitsuba_manifold.basis.blend import blend  # noqa: E402
from mitsuba_manifold.imaging import io as imageio  # noqa: E402

small_basis, explorer, server = test_explore.small_basis, test_explore.explorer, test_explore.server


@pytest.fixture(scope="module")
def client(explorer):
    with TestClient(test_explore.app_for(explorer)) as c:
        yield c


def _exr_url(img, tmp_path):
    path = str(tmp_path / "photo.exr")
    imageio.write_exr(path, np.asarray(img, np.float32))
    with open(path, "rb") as f:
        return "data:image/x-exr;base64," + base64.b64encode(f.read()).decode()


def _png_url(rgb8):
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb8).save(buf, format="PNG")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _wait(client, job, limit=600):
    end = time.monotonic() + limit
    while job["state"] in ("queued", "running"):
        assert time.monotonic() < end, job
        time.sleep(0.2)
        r = client.get(f"/api/acquire/{job['id']}")
        assert r.status_code == 200, r.text
        job = r.json()
    return job


def _photo_of(explorer, w):
    """The basis's image of weights ``w`` (its full blend, as the page shows it)."""
    basis = explorer.basis(None)
    img, _ = blend(basis, explorer.manifold, w=w, prune=0.0, l2="raw")
    return img


def test_a_photo_of_a_known_combination_is_recovered(explorer, client, tmp_path):
    names = list(explorer.manifold.names)
    w_true = np.zeros(len(names))
    w_true[1], w_true[4] = 0.65, 0.35
    photo = _photo_of(explorer, w_true)
    r = client.post("/api/acquire", json={"basis": "", "photo": _exr_url(photo, tmp_path)})
    assert r.status_code == 200, r.text
    job = _wait(client, r.json())
    assert job["state"] == "done", job
    res = job["result"]
    w = np.array([res["weights"][n] for n in names])
    # the photo is explained (its relative error), and by the weights that made it
    assert res["error"] < 0.02, res["error"]
    assert np.abs(w - w_true).max() < 0.1, dict(zip(names, w.round(3)))
    assert res["description"].startswith(f"{w[np.argmax(np.abs(w))]:.2f} {names[1]}")
    assert names[1] in res["description"] and names[4] in res["description"]
    assert res["single"]["name"] in names
    # a convex combination of two measured materials: close to a latent point or named
    assert res["latent"]["on_map"] == (res["x"] is not None)
    assert len(res["latent"]["x"]) == explorer.manifold.q
    assert 'type="manifold_brdf"' in res["snippet"]
    # the images: the acquired material in the scene is the photo, the sheet has three tiles
    png = client.get(f"/api/acquire/{job['id']}/acquired.png")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    from PIL import Image

    acquired = np.asarray(Image.open(io.BytesIO(png.content)).convert("RGB"), np.float64)
    target = np.asarray(
        Image.open(io.BytesIO(client.get(f"/api/acquire/{job['id']}/target.png").content)).convert(
            "RGB"
        ),
        np.float64,
    )
    assert np.abs(acquired - target).mean() < 3.0
    sheet = Image.open(io.BytesIO(client.get(f"/api/acquire/{job['id']}/sheet.png").content))
    assert sheet.width >= 3 * explore_acquire.SHEET_TILE


def test_a_photo_of_a_latent_point_is_placed_on_the_map(explorer, client, tmp_path):
    m = explorer.manifold
    i = 3
    photo, _ = blend(explorer.basis(None), m, x=m.latent[i], prune=0.0, l2="raw")
    r = client.post("/api/acquire", json={"photo": _exr_url(photo, tmp_path)})
    job = _wait(client, r.json())
    assert job["state"] == "done", job
    res = job["result"]
    assert res["latent"]["on_map"] and res["x"] is not None
    np.testing.assert_allclose(res["x"], m.latent[i], atol=0.05)
    assert res["description"].split(" + ")[0].endswith(m.names[i])
    assert res["weights"][m.names[i]] > 0.9 and res["beyond"] == []


def test_a_resized_png_photo_and_a_mask_are_taken(explorer, client):
    w_true = np.zeros(explorer.manifold.n)
    w_true[2] = 1.0
    photo = _photo_of(explorer, w_true)
    big = np.repeat(np.repeat(photo, 2, axis=0), 2, axis=1)  # twice the basis's size
    rgb8 = (255 * imageio.srgb_encode(np.clip(big, 0, 1))).round().astype(np.uint8)
    mask = np.zeros(photo.shape[:2], np.uint8)
    mask[8:24, 8:24] = 255
    r = client.post(
        "/api/acquire",
        json={"photo": _png_url(rgb8), "mask": _png_url(np.stack([mask] * 3, axis=-1))},
    )
    assert r.status_code == 200, r.text
    job = _wait(client, r.json())
    assert job["state"] == "done", job
    res = job["result"]
    h, w = photo.shape[:2]
    assert any(f"resized from {2 * w}x{2 * h}" in n for n in res["notes"])
    assert res["pixels"] <= 16 * 16
    assert max(res["weights"], key=lambda n: abs(res["weights"][n])) == explorer.manifold.names[2]


@pytest.mark.parametrize(
    "body, words",
    [
        ({"photo": "not base64 at all!"}, "base64"),
        (
            {"photo": "data:image/png;base64," + base64.b64encode(b"hello").decode()},
            "not an OpenEXR, PNG or JPEG",
        ),
        ({}, "`photo`"),
        ({"photo": "x", "basis": "nope"}, "unknown basis"),
        ("[1, 2]", "JSON object"),
        (
            {
                "photo": _png_url(np.full((32, 32, 3), 128, np.uint8)),
                "mask": _png_url(np.zeros((32, 32, 3), np.uint8)),
            },
            "the mask selects no pixel",
        ),
    ],
)
def test_a_bad_upload_answers_one_line(client, body, words):
    if isinstance(body, str):
        r = client.post("/api/acquire", content=body)
    else:
        r = client.post("/api/acquire", json=body)
    assert r.status_code == 400, r.text
    msg = r.json()["error"]
    assert words in msg and "\n" not in msg and "Traceback" not in msg


def test_a_photo_of_another_aspect_is_refused(explorer, client):
    rgb8 = np.full((16, 40, 3), 128, np.uint8)
    r = client.post("/api/acquire", json={"photo": _png_url(rgb8)})
    assert r.status_code == 400
    assert "aspect ratios differ" in r.json()["error"]


def test_a_cross_origin_upload_is_refused(explorer, client):
    rgb8 = np.full((32, 32, 3), 128, np.uint8)
    before = len(explorer.acquisitions._jobs)
    r = client.post(
        "/api/acquire",
        json={"photo": _png_url(rgb8)},
        headers={"Origin": "http://evil.example"},
    )
    assert r.status_code == 403 and "cross-origin" in r.json()["error"]
    assert len(explorer.acquisitions._jobs) == before  # nothing started


def test_an_upload_beyond_the_limit_is_refused_before_parsing(client):
    body = b"x" * (explore_acquire.MAX_UPLOAD + 1)
    r = client.post("/api/acquire", content=body)
    assert r.status_code == 413 and "larger than" in r.json()["error"]


def test_a_combination_leaving_the_simplex_is_named_so():
    names = ["gold-paint", "steel", "felt"]
    text, why = explore_acquire.describe(names, [0.62, 0.31, -0.05])
    assert text == "0.62 gold-paint + 0.31 steel - 0.05 felt"
    assert why and "negative" in why[0]
    text, why = explore_acquire.describe(names, [0.7, 0.3, 0.0])
    assert why == [] and text == "0.70 gold-paint + 0.30 steel"


@test_explore.browser_only
def test_the_page_acquires_a_photo_and_goes_to_its_point(
    server, small_basis, small_manifold_paper, tmp_path
):
    """In headless Chromium: a photo of a measured material's point chosen in the panel, Acquire:
    the panel names it, shows the sheet and the weights, and "go to it" moves the explorer there."""
    from playwright.sync_api import sync_playwright

    from mitsuba_manifold.basis.folder import Basis
    from mitsuba_manifold.manifold.model import Manifold

    m = Manifold.load(small_manifold_paper)
    i = 3
    photo, _ = blend(Basis.load(small_basis), m, x=m.latent[i], prune=0.0, l2="raw")
    path = str(tmp_path / "photo.exr")
    imageio.write_exr(path, photo)
    with sync_playwright() as p:
        b = p.chromium.launch(
            executable_path=test_explore.CHROMIUM,
            args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"],
        )
        try:
            pg = b.new_page(viewport={"width": 1500, "height": 1000})
            errors = []
            pg.on("pageerror", lambda e: errors.append(str(e)))
            pg.goto(server)
            pg.wait_for_function("window.explore && window.explore.state.map", timeout=60000)
            assert pg.is_disabled("#acq-start")  # nothing chosen yet
            pg.set_input_files("#acq-photo", path)
            pg.click("#acq-start")
            pg.wait_for_function(
                "window.explore.state.acquired && window.explore.state.acquired.state === 'done'",
                timeout=300000,
            )
            assert m.names[i] in pg.inner_text("#acq-name")
            pg.wait_for_function(
                "document.getElementById('acq-sheet').complete && "
                "document.getElementById('acq-sheet').naturalWidth > 0"
            )
            assert pg.locator("#acq-weights .name").count() >= 1
            pg.click("#acq-where button")  # on the map: go there
            pg.wait_for_function(
                f"window.explore.state.x && Math.abs(window.explore.state.x[0] - {m.latent[i][0]}) < 0.05"
            )
            assert not errors, errors
        finally:
            b.close()


@pytest.fixture(scope="module")
def gi_explorer(small_manifold, tmp_path_factory):
    """An explorer of a full-GI basis of the table (the object sees itself: L2+ and cross terms)."""
    import mitsuba as mi

    import mitsuba_manifold
    from mitsuba_manifold.apps.explore import Explorer
    from mitsuba_manifold.render.jobs import render_basis

    mi.set_variant("llvm_ad_rgb")
    mitsuba_manifold.register()
    out = tmp_path_factory.mktemp("acquire_gi") / "basis"
    render_basis.render_basis(
        "table", small_manifold, out, spp=4, mode="onepass", components="full", resolution=24
    )
    ex = Explorer([str(out)], manifold=small_manifold, load_tables=False)
    yield ex
    ex.close()


def test_a_full_gi_photo_is_solved_on_the_full_gi_images(gi_explorer):
    """A photo with interreflection (the basis's full blend, cross terms included): solved on the
    materials' full-GI images, the cross terms left out of the solve; the weights come back."""
    ex = gi_explorer
    basis = ex.basis(None)
    assert "l2+" in basis.components
    names = list(ex.manifold.names)
    w_true = np.zeros(len(names))
    w_true[names.index("gold-paint")], w_true[names.index("white-diffuse-bball")] = 0.6, 0.4
    photo, info = blend(basis, ex.manifold, w=w_true, prune=0.0, l2="raw")
    assert info.component == "full"
    answer, images = explore_acquire.acquire_photo(ex, None, photo, None, [])
    assert "full GI" in answer["model"] and answer["blend"] == "full"
    w = np.array([answer["weights"][n] for n in names])
    assert np.abs(w - w_true).max() < 0.1, dict(zip(names, w.round(3)))
    assert answer["error"] < 0.05
    # the image shown is the basis's full blend at the acquired weights
    shown, _ = blend(basis, ex.manifold, w=w, prune=0.0)
    np.testing.assert_allclose(images["acquired"], shown, rtol=1e-5, atol=1e-6)


def test_one_acquisition_at_a_time_and_a_failure_is_one_line(explorer, client, monkeypatch):
    import threading

    from mitsuba_manifold.errors import InputError

    go = threading.Event()

    def slow(ex, name, target, mask, notes, progress):
        progress("solving", 0.5)
        go.wait(30)
        raise InputError("the photo explains nothing\nsecond line")

    monkeypatch.setattr(explore_acquire, "acquire_photo", slow)
    photo = {"photo": _png_url(np.full((32, 32, 3), 128, np.uint8))}
    first = client.post("/api/acquire", json=photo)
    assert first.status_code == 200, first.text
    second = client.post("/api/acquire", json=photo)
    assert second.status_code == 429 and "running" in second.json()["error"]
    go.set()
    job = _wait(client, first.json())
    assert job["state"] == "failed" and job["message"] == "the photo explains nothing"
    r = client.get(f"/api/acquire/{job['id']}/sheet.png")
    assert r.status_code == 400 and "failed" in r.json()["error"]
    assert client.get("/api/acquire/a999999").status_code == 400
    assert client.get("/api/acquire/../etc").status_code in (400, 404)
