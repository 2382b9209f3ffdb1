"""Benchmark of ``tools/explore.py``: request -> encoded image, end to end over a websocket.

Starts the real server (``python3 -m mitsuba_manifold.apps.cli.explore``, its own process, on
127.0.0.1 and a free port) on a basis, connects a websocket client from this process and
times, for random latent points inside the data, the wall time from sending a
frame request to receiving the encoded image (blend over the materials kept by pruning,
tonemap, encode, websocket transfer), per encoding. Targets (issue 11): at most 30 ms at
256x256 and 60 ms at 512x512 for N = 100. Without a basis of the larger size a copy of the
given basis upsampled 2x per axis (nearest) is written to a temporary folder: the time
depends on N and the pixel count only.
"""

import json
import os
import shutil
import struct
import tempfile
import time

import numpy as np

from ..explore import launch

TARGET_MS = {256 * 256: 30.0, 512 * 512: 60.0}


def upsampled_basis(folder, out, factor=2):
    """Copy of a basis with every image upsampled ``factor`` x (nearest); returns ``out``."""
    from ...imaging import io as imageio
    from ...basis.folder import read_manifest, write_manifest

    manifest = read_manifest(folder)
    os.makedirs(out, exist_ok=True)
    for key, entry in manifest["images"].items():
        img = imageio.read_exr(os.path.join(folder, entry["file"]))
        imageio.write_exr(os.path.join(out, entry["file"]), img.repeat(factor, 0).repeat(factor, 1))
    manifest = dict(manifest, resolution=[v * factor for v in manifest["resolution"]])
    write_manifest(out, manifest)
    return out


def _time_frames(ws_url, points, fmt, basis):
    from websockets.sync.client import connect

    times, sizes, server_ms = [], [], []
    with connect(ws_url, max_size=None) as ws:
        for seq, x in enumerate(points):
            t0 = time.perf_counter()
            ws.send(json.dumps({"type": "frame", "seq": seq, "x": list(map(float, x)), "format": fmt,
                                "basis": basis}))
            msg = ws.recv()
            times.append(1e3 * (time.perf_counter() - t0))
            n = struct.unpack("<I", msg[:4])[0]
            meta = json.loads(msg[4:4 + n])
            if meta["type"] != "frame":
                raise RuntimeError(f"frame request failed: {meta}")
            sizes.append(len(msg) - 4 - n)
            server_ms.append({k: meta[k] for k in ("blend_ms", "tonemap_ms", "encode_ms", "total_ms", "n_images")})
    return times, sizes, server_ms


def _stats(values):
    v = np.asarray(values, dtype=np.float64)
    return {"median": float(np.median(v)), "p90": float(np.percentile(v, 90)), "max": float(v.max())}


def run(basis, manifold=None, requests=60, formats=("rgba", "jpeg", "png"), upsample=True, seed=0,
        screenshot_path=None):
    """Frame latency per basis size and encoding (see the module docstring); with
    ``screenshot_path`` also a screenshot of the page (:func:`screenshot`)."""
    from ...basis.folder import read_manifest
    from ...manifold.model import Manifold

    folders = [os.path.abspath(basis)]
    tmp = None
    if upsample:
        tmp = tempfile.mkdtemp(prefix="bench_explore_")
        folders.append(upsampled_basis(basis, os.path.join(tmp, "basis_x2")))
    report = {"requests": requests, "formats": list(formats), "client": "websockets (another process)",
              "load_average_1min_before": os.getloadavg()[0], "sizes": []}
    proc = None
    try:
        m = Manifold.load(manifold or read_manifest(basis)["manifold"])
        rng = np.random.default_rng(seed)
        # points inside the data: between random pairs of latent points
        i, j = rng.integers(0, m.n, (2, requests))
        t = rng.uniform(0.2, 0.8, (requests, 1))
        points = (1 - t) * m.latent[i] + t * m.latent[j]
        proc, base = launch.start(folders, manifold, ["--no-tables"])
        ws_url = base.replace("http://", "ws://") + "ws"
        for folder in folders:
            manifest = read_manifest(folder)
            w, h = manifest["resolution"]
            name = os.path.basename(folder)
            row = {"basis": folder, "upsampled": folder != folders[0], "resolution": [w, h],
                   "n_materials": len(manifest["images"]) - 1, "target_ms": TARGET_MS.get(w * h), "formats": {}}
            for fmt in formats:
                _time_frames(ws_url, points[:3], fmt, name)   # warm-up
                times, sizes, server_ms = _time_frames(ws_url, points, fmt, name)
                row["formats"][fmt] = {
                    "request_to_image_ms": _stats(times), "bytes": _stats(sizes),
                    "server_total_ms": _stats([s["total_ms"] for s in server_ms]),
                    "blend_ms": _stats([s["blend_ms"] for s in server_ms]),
                    "tonemap_ms": _stats([s["tonemap_ms"] for s in server_ms]),
                    "encode_ms": _stats([s["encode_ms"] for s in server_ms]),
                    "images_blended": _stats([s["n_images"] for s in server_ms])}
                if row["target_ms"]:
                    row["formats"][fmt]["meets_target"] = _stats(times)["median"] <= row["target_ms"]
            report["sizes"].append(row)
        report["load_average_1min_after"] = os.getloadavg()[0]
    finally:
        if proc is not None:
            launch.stop(proc)
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    if screenshot_path:
        report["screenshot"] = screenshot(basis, screenshot_path, manifold)
    return report


def screenshot(basis, path, manifold=None, reference_spp=256, size=(1560, 1000), zoom_steps=12):
    """PNG of the page (system Chromium through Playwright): a path between a material near the
    centre of the data and its latent neighbour, scrubbed half-way, the map zoomed in on it, with
    a reference render.

    Returns ``path``, or None when Chromium or Playwright is missing."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    chromium = launch.find_chromium()
    if chromium is None:
        return None
    proc, url = launch.start([basis], manifold)
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox", "--use-angle=swiftshader",
                                                                        "--enable-unsafe-swiftshader"])
            page = browser.new_context(viewport={"width": size[0], "height": size[1]}).new_page()
            page.goto(url)
            page.wait_for_function("window.explore && window.explore.state.displayed && window.explore.state.map && "
                                   "window.explore.state.info.tables !== 'loading'", timeout=120000)
            latent = np.array(page.evaluate("window.explore.state.info.latent"))
            a = int(np.argmin(((latent - latent.mean(axis=0)) ** 2).sum(axis=1)))
            d = ((latent - latent[a]) ** 2).sum(axis=1)
            d[a] = np.inf
            b = int(np.argmin(d))
            for index, button in ((a, "#set-a"), (b, "#set-b")):
                page.evaluate(f"window.explore.setX(window.explore.state.info.latent[{index}])")
                page.wait_for_timeout(300)
                page.click(button)
            page.fill("#scrub", "500")
            page.dispatch_event("#scrub", "input")
            box = page.locator("#map").bounding_box()   # zoom in on the path
            xy = page.evaluate("""() => { const s = window.explore.state, c = document.getElementById('map');
                const r = c.getBoundingClientRect(), [x0, x1, y0, y1] = s.map.extent;
                return [r.left + (s.x[s.dims[0]] - x0) / (x1 - x0) * r.width,
                        r.top + (1 - (s.x[s.dims[1]] - y0) / (y1 - y0)) * r.height]; }""")
            page.mouse.move(*xy)
            for _ in range(zoom_steps):
                page.mouse.wheel(0, -100)
                page.wait_for_timeout(150)
            page.mouse.move(box["x"] + box["width"] + 40, box["y"])
            if page.is_enabled("#ref-start"):   # the basis's scene is there
                page.select_option("#ref-spp", str(reference_spp))
                page.click("#ref-start")
                page.wait_for_selector("#ref-result:not([hidden])", timeout=600000)
                page.dispatch_event("#exposure", "input")   # a frame timed without the render beside it
            page.wait_for_timeout(1500)
            png = page.screenshot(full_page=True)
            browser.close()
    finally:
        launch.stop(proc)
    from ..._util.atomic import write_bytes
    write_bytes(path, png)
    return path
