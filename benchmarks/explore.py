"""Benchmark of ``tools/explore.py``: request -> encoded image, end to end over a websocket.

Starts the real server (``python3 -m mitsuba_manifold.apps.cli.explore``, its own process, on
127.0.0.1 and a free port) on a basis, connects a websocket client from this process and
times, for random latent points inside the data, the wall time from sending a
frame request to receiving the encoded image (blend over the materials kept by pruning,
tonemap, encode, websocket transfer), per encoding. Targets: at most 30 ms at
256x256 and 60 ms at 512x512 for N = 100. Without a basis of the larger size a copy of the
given basis upsampled 2x per axis (nearest) is written to a temporary folder: the time
depends on N and the pixel count only.

With ``browser=True`` (``tools/bench.py explore --browser``) it measures the page itself
instead (:func:`browser`): in headless Chromium, drags of 60 pointer moves over the latent
map, by default delivered in the page at 60 Hz as a mouse's moves (``driver="page"``;
``"playwright"``: one Playwright ``mouse.move`` per move, a round trip each, which delivers fewer
moves a second and takes CPU from the page), timed from each pointer move to the first scene
frame drawn for that point or a later one; the images per second (the frames of distinct points
of the drag drawn, over the time from its first move to the last of them drawn) beside the pointer
moves per second delivered; the sphere's redraws; the time from opening the URL to the material
tables being ready; then the same drags again while a 4096-spp reference render runs (started
and, after them, cancelled from the page: how long the cancel takes). Targets: median <= 50 ms,
p90 <= 120 ms, >= 20 images/s, tables <= 5 s, and a reference render keeping at least half the
image rate. The load averages (1, 5, 15 min) at each part go with them.

Chromium runs WebGL on SwiftShader (there is no GPU) and, by default (``compositing="software"``),
composites the page on the CPU, as Chrome does on a machine without a GPU;
``compositing="swiftshader"`` composites it through SwiftShader's GL too (the measurements before
2026-12-02), where every frame redraws the whole viewport in software GL (on the 2-core
machine about 150 ms per frame at 1500x1000 under load; 65 ms at 800x600).
"""

import json
import os
import shutil
import struct
import tempfile
import time

import numpy as np

from mitsuba_manifold.apps.explore.web import launch

TARGET_MS = {256 * 256: 30.0, 512 * 512: 60.0}


def upsampled_basis(folder, out, factor=2):
    """Copy of a basis with every image upsampled ``factor`` x (nearest); returns ``out``."""
    from dataclasses import replace

    from mitsuba_manifold._util.cache import file_hash
    from mitsuba_manifold.basis.folder import Manifest
    from mitsuba_manifold.imaging import io as imageio

    manifest = Manifest.read(folder)
    os.makedirs(out, exist_ok=True)
    images = {}
    for key, entry in manifest.images.items():
        img = imageio.read_exr(os.path.join(folder, entry.file))
        imageio.write_exr(os.path.join(out, entry.file), img.repeat(factor, 0).repeat(factor, 1))
        images[key] = replace(entry, sha256=file_hash(os.path.join(out, entry.file)))
    size = tuple(v * factor for v in manifest.resolution)
    replace(manifest, images=images, settings=replace(manifest.settings, resolution=size)).write(
        out
    )
    return out


def _time_frames(ws_url, points, fmt, basis):
    from websockets.sync.client import connect

    times, sizes, server_ms = [], [], []
    with connect(ws_url, max_size=None) as ws:
        for seq, x in enumerate(points):
            t0 = time.perf_counter()
            ws.send(
                json.dumps(
                    {
                        "type": "frame",
                        "seq": seq,
                        "x": list(map(float, x)),
                        "format": fmt,
                        "basis": basis,
                        "coarse": True,
                    }
                )
            )  # a drag's frames (the page's)
            msg = ws.recv()
            times.append(1e3 * (time.perf_counter() - t0))
            n = struct.unpack("<I", msg[:4])[0]
            meta = json.loads(msg[4 : 4 + n])
            if meta["type"] != "frame":
                raise RuntimeError(f"frame request failed: {meta}")
            sizes.append(len(msg) - 4 - n)
            server_ms.append(
                {
                    k: meta[k]
                    for k in ("blend_ms", "tonemap_ms", "encode_ms", "total_ms", "n_images")
                }
            )
    return times, sizes, server_ms


def _stats(values):
    v = np.asarray(values, dtype=np.float64)
    return {
        "median": float(np.median(v)),
        "p90": float(np.percentile(v, 90)),
        "max": float(v.max()),
    }


def run(  # noqa: PLR0913  tools/bench.py's options, as keywords
    basis,
    manifold=None,
    requests=60,
    formats=("rgba", "jpeg", "png"),
    upsample=True,
    seed=0,
    screenshot_path=None,
    browser=False,
    compositing="software",
    driver="page",
):
    """Frame latency per basis size and encoding (see the module docstring); with
    ``screenshot_path`` also a screenshot of the page (:func:`screenshot`); with ``browser``
    the page's own latency instead (:func:`browser`).
    """
    if browser:
        report = globals()["browser"](basis, manifold, compositing=compositing, driver=driver)
        if screenshot_path:  # a short reference render beside the page's timing run
            report["screenshot"] = screenshot(basis, screenshot_path, manifold, reference_spp=64)
        return report
    from mitsuba_manifold.basis.folder import Manifest
    from mitsuba_manifold.manifold.model import Manifold

    folders = [os.path.abspath(basis)]
    tmp = None
    if upsample:
        tmp = tempfile.mkdtemp(prefix="bench_explore_")
        folders.append(upsampled_basis(basis, os.path.join(tmp, "basis_x2")))
    report = {
        "requests": requests,
        "formats": list(formats),
        "client": "websockets (another process)",
        "load_average_1min_before": os.getloadavg()[0],
        "sizes": [],
    }
    proc = None
    try:
        m = Manifold.load(manifold or Manifest.read(basis).manifold)
        rng = np.random.default_rng(seed)
        # points inside the data: between random pairs of latent points
        i, j = rng.integers(0, m.n, (2, requests))
        t = rng.uniform(0.2, 0.8, (requests, 1))
        points = (1 - t) * m.latent[i] + t * m.latent[j]
        proc, base = launch.start(folders, manifold, ["--no-tables"])
        ws_url = base.replace("http://", "ws://") + "ws"
        for folder in folders:
            manifest = Manifest.read(folder)
            w, h = manifest.resolution
            name = os.path.basename(folder)
            row = {
                "basis": folder,
                "upsampled": folder != folders[0],
                "resolution": [w, h],
                "n_materials": len(manifest.images) - 1,
                "target_ms": TARGET_MS.get(w * h),
                "formats": {},
            }
            for fmt in formats:
                _time_frames(ws_url, points[:3], fmt, name)  # warm-up
                times, sizes, server_ms = _time_frames(ws_url, points, fmt, name)
                row["formats"][fmt] = {
                    "request_to_image_ms": _stats(times),
                    "bytes": _stats(sizes),
                    "server_total_ms": _stats([s["total_ms"] for s in server_ms]),
                    "blend_ms": _stats([s["blend_ms"] for s in server_ms]),
                    "tonemap_ms": _stats([s["tonemap_ms"] for s in server_ms]),
                    "encode_ms": _stats([s["encode_ms"] for s in server_ms]),
                    "images_blended": _stats([s["n_images"] for s in server_ms]),
                }
                if row["target_ms"]:
                    row["formats"][fmt]["meets_target"] = (
                        _stats(times)["median"] <= row["target_ms"]
                    )
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


BROWSER_TARGETS = {
    "median_ms": 50.0,
    "p90_ms": 120.0,
    "images_per_s": 20.0,
    "tables_ready_s": 5.0,
    "rate_with_reference": 0.5,
}
#: How Chromium composites the page (see the module docstring).
COMPOSITING = ("software", "swiftshader")


def _launch_chromium(p, compositing="software"):
    if compositing not in COMPOSITING:
        raise ValueError(f"compositing must be one of {COMPOSITING}, got {compositing!r}")
    return p.chromium.launch(
        executable_path=launch.find_chromium(),
        args=["--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
        + (["--disable-gpu-compositing"] if compositing == "software" else []),
    )


#: When each part of "tables ready" came (seconds from the page's start, polled every 20 ms):
#: the page's info, the tables loaded, the sphere's first table, the map, the first frame.
_READY_PARTS = """window.__ready = {}; const __t = setInterval(() => {
  const e = window.explore, s = e && e.state, r = window.__ready, now = performance.now() / 1e3;
  const parts = { info: s && s.info, tables: s && s.info && s.info.tables !== "loading",
                  sphere_table: s && s.previewX, map: s && s.map, frame: s && s.displayed };
  for (const k in parts) if (parts[k] && r[k] === undefined) r[k] = now;
  if (Object.keys(r).length === Object.keys(parts).length) clearInterval(__t); }, 20);"""


def _process_kind(pid):
    """What a process under this one is: Chromium's ``--type`` (``renderer``, ``gpu-process``,
    ...; ``browser`` without one) or ``driver`` (Playwright's, anything else).
    """
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            args = f.read().replace(b" ", b"\0").split(b"\0")  # Chromium's children: one string
    except OSError:
        return "driver"
    if not args or b"chrom" not in os.path.basename(args[0]).lower():
        return "driver"
    kinds = [a[len(b"--type=") :].decode() for a in args if a.startswith(b"--type=")]
    return kinds[0] if kinds else "browser"


def _cpu_seconds(server_pid):
    """CPU seconds (user + system, from ``/proc``) of the processes started from this one:
    ``{"server": the explorer's process tree, "browser": every other descendant (Chromium's
    processes and Playwright's driver), "browser:KIND": the part of it of each kind of process
    (:func:`_process_kind`)}``; empty where ``/proc`` is missing. A difference of two readings
    is the work a drag costs, whatever else runs on the machine.
    """
    tick, parent, cpu = os.sysconf("SC_CLK_TCK"), {}, {}
    if not os.path.isdir("/proc/self"):
        return {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat") as f:
                fields = f.read().rsplit(")", 1)[1].split()
        except OSError:  # gone meanwhile
            continue
        parent[int(name)] = int(fields[1])
        cpu[int(name)] = (int(fields[11]) + int(fields[12])) / tick

    def under(pid, root):
        while pid > 1:
            if pid == root:
                return True
            pid = parent.get(pid, 0)
        return False

    me, out = os.getpid(), {"server": 0.0, "browser": 0.0}
    for pid, seconds in cpu.items():
        if under(pid, server_pid):
            out["server"] += seconds
        elif pid != me and under(pid, me):
            out["browser"] += seconds
            kind = "browser:" + _process_kind(pid)
            out[kind] = out.get(kind, 0.0) + seconds
    return out


def _settle(server_pid, share=0.1, window=1.0, timeout=120.0):
    """Wait until the explorer's process uses under ``share`` of a core over ``window`` s (the
    work after the tables, e.g. the perceptual metric, done), at most ``timeout`` s; returns the
    seconds waited.
    """
    t0 = time.perf_counter()
    last = _cpu_seconds(server_pid).get("server")
    while last is not None and time.perf_counter() - t0 < timeout:
        time.sleep(window)
        now = _cpu_seconds(server_pid)["server"]
        if now - last < share * window:
            break
        last = now
    return time.perf_counter() - t0


def _cpu_per_move(before, after, moves):
    """Milliseconds of CPU per pointer move, per part and in all (``total``: server and
    browser), between two :func:`_cpu_seconds` (a process started between them counts whole).
    """
    if not before or not moves:
        return None
    out = {k: 1e3 * (after.get(k, 0.0) - before.get(k, 0.0)) / moves for k in after}
    out["total"] = out["server"] + out["browser"]
    return out


#: How a drag's pointer moves reach the page (:func:`_drag`).
DRIVERS = ("page", "playwright")
#: The pointer moves' pace of the ``page`` driver: a 60 Hz display's frame (a real mouse's moves
#: reach the page at the display's rate, one per frame).
PACE_MS = 1000.0 / 60.0

#: The ``page`` driver's moves: the pointer pressed on the map for real (Playwright's
#: ``mouse.down``: a trusted press, so the map holds the pointer's capture as for a real press),
#: then ``moves`` ``pointermove`` events dispatched in the page at ``pace`` ms from each other
#: (timers aimed at fixed times from the first, so a late one does not shift the rest) on the
#: element a real move goes to (the one holding pointer 1's capture, else the one under the
#: point), each as a mouse's move with the button held. A timer that fires late delivers only
#: the newest position due, as Chrome does with real moves that wait for a busy page (one
#: ``pointermove`` per frame, the others coalesced into it). Resolves once the last move is
#: delivered: ``{captured, delivered, coalesced, targets, steps}`` (``targets``: how many moves
#: went to each element, by id; ``steps``: which of the ``moves`` positions were delivered).
_PAGE_MOVES = """([a, b, moves, pace]) => new Promise((resolve) => {
  const map = document.getElementById("map"), captured = map.hasPointerCapture(1), targets = {};
  let k = 0, delivered = 0, coalesced = 0, steps = [];
  const t0 = performance.now();
  const tick = () => {
    const due = Math.max(k + 1, Math.min(moves, Math.floor((performance.now() - t0) / pace + 1e-3)));
    coalesced += Math.max(0, due - k - 1);
    k = due;
    const x = a[0] + (b[0] - a[0]) * k / moves, y = a[1] + (b[1] - a[1]) * k / moves;
    const el = map.hasPointerCapture(1) ? map : document.elementFromPoint(x, y) || document.body;
    targets[el.id || el.tagName] = (targets[el.id || el.tagName] || 0) + 1;
    el.dispatchEvent(new PointerEvent("pointermove", { bubbles: true, cancelable: true, composed: true,
      view: window, pointerId: 1, pointerType: "mouse", isPrimary: true, clientX: x, clientY: y,
      screenX: x, screenY: y, button: -1, buttons: 1, width: 1, height: 1, pressure: 0.5 }));
    delivered++; steps.push(k);
    if (k >= moves) resolve({ captured, delivered, coalesced, targets, steps });
    else setTimeout(tick, Math.max(0, t0 + k * pace - performance.now()));
  };
  setTimeout(tick, pace);
})"""


def _drag(page, a, b, moves, pace_ms, driver="page"):
    """One drag from page point ``a`` to ``b`` in ``moves`` pointer moves (``driver``: ``"page"``,
    :data:`_PAGE_MOVES`; ``"playwright"``: a Playwright ``mouse.move`` then a ``pace_ms`` wait per
    move, each a round trip from this process, so fewer moves a second than the pace says).

    Returns a dict: ``latencies`` (ms from each move to the first frame drawn for that move or a
    later one), ``images`` (the frames drawn of distinct points of the drag's moves, each counted
    once), ``image_span_s`` (from the first move to the last of those frames drawn),
    ``moves`` (pointer moves the page handled), ``move_span_s`` (first to last move), ``draws``
    (the sphere's redraws), ``parts`` (per frame: the server's ms and the round trip's) and, for
    the page driver, ``delivery`` (what :data:`_PAGE_MOVES` returned).
    """
    if driver not in DRIVERS:
        raise ValueError(f"driver must be one of {DRIVERS}, got {driver!r}")
    page.mouse.move(*a)
    page.mouse.down()
    # logged from the press on: the moves of the drag, not the one to where it starts
    page.evaluate("""() => { const s = window.explore.state; window.explore.trace = [];
        window.__moves = []; window.__log = () => window.__moves.push({ t: performance.now(), x: s.x.slice() });
        window.addEventListener("pointermove", window.__log);
        window.__draws = window.explore.preview ? window.explore.preview.draws : 0; }""")
    delivery = None
    if driver == "page":
        delivery = page.evaluate(_PAGE_MOVES, [list(a), list(b), moves, pace_ms])
    else:
        for k in range(1, moves + 1):
            page.mouse.move(a[0] + (b[0] - a[0]) * k / moves, a[1] + (b[1] - a[1]) * k / moves)
            page.wait_for_timeout(pace_ms)
    page.mouse.up()
    page.wait_for_function(
        """() => { const m = window.__moves, s = window.explore.state;
        return m.length && s.displayed && s.displayed.x.every((v, k) => v === m[m.length - 1].x[k]); }""",
        timeout=30000,
    )
    out = page.evaluate("""() => { window.removeEventListener("pointermove", window.__log);
        return { moves: window.__moves, frames: window.explore.trace,
                 draws: (window.explore.preview ? window.explore.preview.draws : 0) - window.__draws }; }""")
    return _drag_numbers(out, delivery)


def _drag_numbers(out, delivery=None):
    """:func:`_drag`'s numbers from the page's log of one drag: ``out["moves"]`` (per move
    handled: ``t``, its time, and ``x``, the point it set), ``out["frames"]`` (per frame drawn:
    ``x``, ``at``, ``server_ms``, ``round_trip_ms``) and ``out["draws"]``.
    """
    moves, frames = out["moves"], out["frames"]
    index = {}
    for i, m in enumerate(moves):
        index.setdefault(tuple(m["x"]), i)
    t_first = moves[0]["t"] if moves else 0.0
    drawn, first_draw = [], {}
    for f in frames:
        i = index.get(tuple(f["x"]))
        if i is None or f["at"] < t_first:
            continue
        drawn.append((i, f["at"]))
        first_draw.setdefault(i, f["at"])  # a point drawn again (its rest frame) counts once
    latencies = []
    for i, m in enumerate(moves):
        later = [at for j, at in drawn if j >= i and at >= m["t"]]
        if later:
            latencies.append(min(later) - m["t"])
    parts = [
        (f["server_ms"], f["round_trip_ms"]) for f in frames if f.get("round_trip_ms") is not None
    ]
    last_image = max(first_draw.values(), default=t_first)
    return {
        "latencies": latencies,
        "images": len(first_draw),
        "image_span_s": (last_image - t_first) / 1e3,
        "moves": len(moves),
        "move_span_s": (moves[-1]["t"] - t_first) / 1e3 if moves else 0.0,
        "draws": out["draws"],
        "parts": parts,
        "delivery": delivery,
    }


def _drags(page, at, latent, drags, moves, pace_ms, seed=0, driver="page"):
    """``drags`` drags of ``moves`` moves (:func:`_drag`) between random pairs of materials
    (off their points); returns :func:`_drag`'s numbers summed over the drags (``latencies`` and
    ``parts`` joined, ``delivery`` a list).
    """
    rng = np.random.default_rng(seed)
    total = {"latencies": [], "parts": [], "delivery": []}
    for _ in range(drags):
        i, j = rng.choice(len(latent), 2, replace=False)
        # between materials, off their points (no snapping): every move is a new point
        a, b = [0.8 * latent[i] + 0.2 * latent[j] + 0.05, 0.2 * latent[i] + 0.8 * latent[j] + 0.05]
        got = _drag(page, at(a), at(b), moves, pace_ms, driver)
        for k, v in got.items():
            if k == "delivery":
                total[k].append(v)
            else:
                total[k] = total.get(k, 0) + v
    return total


def _rates(d):
    """The report's rates of :func:`_drags`'s numbers ``d``: ``images_per_s`` (the frames of
    distinct points of the drags' moves drawn, over the time from each drag's first move to the
    last of them drawn), ``pointer_moves_per_s`` (the moves the page handled a second, first to
    last move of each drag) and how many of the moves got an image of their own.
    """
    return {
        "images_per_s": d["images"] / d["image_span_s"] if d["image_span_s"] else None,
        "pointer_moves_per_s": (d["moves"] - len(d["delivery"])) / d["move_span_s"]
        if d["move_span_s"]
        else None,
        "images_per_move": d["images"] / d["moves"] if d["moves"] else None,
    }


def _reference_until(page, job, done, timeout):
    """The status of reference job ``job`` (``/api/reference/ID``, fetched by the page) once
    ``done(status)`` holds; polled (``wait_for_function`` would not wait for a fetch's promise).
    """
    deadline = time.monotonic() + timeout
    while True:
        status = page.evaluate(f"fetch('/api/reference/{job}').then((r) => r.json())")
        if done(status):
            return status
        if time.monotonic() > deadline:
            raise RuntimeError(f"reference job {job} did not get there in {timeout} s: {status}")
        time.sleep(0.05)


def _with_reference(page, at, latent, drags, moves, pace_ms, driver="page"):
    """The drags again while a 4096-spp reference render runs (started from the page), then the
    render cancelled from the page: ``{"move_to_frame_ms", "images_per_s", "cancel_s", ...}``.
    """
    if not page.is_enabled("#ref-start"):
        return None
    page.select_option("#ref-spp", "4096")
    page.click("#ref-start")
    page.wait_for_function("window.explore.state.referenceJob", timeout=30000)
    job = page.evaluate("window.explore.state.referenceJob")
    _reference_until(page, job, lambda j: j["progress"] > 0, 120)  # rendering, past its start
    d = _drags(page, at, latent, drags, moves, pace_ms, seed=1, driver=driver)
    state = _reference_until(page, job, lambda j: True, 10)
    cancel_s = None  # None: the render ended before the drags did (a small basis)
    if state["state"] == "rendering" and page.is_visible("#ref-cancel"):
        from playwright.sync_api import TimeoutError as ClickTimeout

        t0 = time.perf_counter()
        try:
            page.click("#ref-cancel", timeout=10000)
        except ClickTimeout:  # the button went: the render ended between the look and the click
            state = _reference_until(page, job, lambda j: j["state"] != "rendering", 10)
        else:
            state = _reference_until(page, job, lambda j: j["state"] != "rendering", 60)
            if state["state"] == "cancelled":  # not "done": the render ended before the click
                cancel_s = time.perf_counter() - t0
    return {
        "move_to_frame_ms": _stats(d["latencies"] or [0]),
        "moves": d["moves"],
        "images": d["images"],
        **_rates(d),
        # where the render was when the cancel took effect (1.0: it had ended first)
        "reference_progress_at_cancel": state["progress"],
        "cancel_s": cancel_s,
        "load_average": os.getloadavg(),
    }


#: What the browser report's numbers are (the report carries it: the JSON reads on its own).
BROWSER_NOTE = (
    "drags of moves_per_drag pointer moves over the latent map, delivered by `driver` ('page': "
    "pointermove events dispatched in the page every pace_ms ms after a real press, as a mouse's "
    "moves at the display's rate; 'playwright': a Playwright mouse.move and a pace_ms wait per "
    "move, a round trip each). move_to_frame_ms: from each move to the first scene frame drawn "
    "for it or a later move. images_per_s: frames drawn of distinct points of the drags' moves, "
    "over the time from each drag's first move to the last such frame drawn. "
    "pointer_moves_per_s: the moves the page handled a second. cpu_ms_per_move: CPU of the "
    "server and of Chromium (with Playwright's driver; browser:KIND per kind of process) per "
    "move, from /proc; cpu_ms_per_image: the same over the images. load_average: "
    "os.getloadavg() (1, 5, 15 min) when each part ended; other jobs on the machine slow every "
    "number but the CPU per move and per image (which their contention still inflates)."
)


def browser(
    basis,
    manifold=None,
    drags=3,
    moves=60,
    pace_ms=PACE_MS,
    chromium=None,
    compositing="software",
    reference=True,
    driver="page",
):
    """The page's latency in headless Chromium (see the module docstring and
    :data:`BROWSER_NOTE`); ``chromium``: a Playwright browser to use (default: the system
    Chromium, launched here, compositing as ``compositing`` says); ``driver``: how the drags'
    moves reach the page (:func:`_drag`).
    """
    if driver not in DRIVERS:
        raise ValueError(f"driver must be one of {DRIVERS}, got {driver!r}")
    if chromium is None:
        from playwright.sync_api import sync_playwright

        with sync_playwright() as p:
            b = _launch_chromium(p, compositing)
            try:
                return browser(
                    basis,
                    manifold,
                    drags,
                    moves,
                    pace_ms,
                    b,
                    compositing,
                    reference=reference,
                    driver=driver,
                )
            finally:
                b.close()
    client = "headless Chromium (WebGL on SwiftShader, " + (
        "software compositing)" if compositing == "software" else "compositing on SwiftShader GL)"
    )
    report = {
        "note": BROWSER_NOTE,
        "driver": driver,
        "drags": drags,
        "moves_per_drag": moves,
        "pace_ms": pace_ms,
        "client": client,
        "load_average_before": os.getloadavg(),
        "targets": BROWSER_TARGETS,
    }
    proc, url = launch.start([basis], manifold, ["--no-thumbnails"])
    try:
        context = chromium.new_context(viewport={"width": 1500, "height": 1000})
        page = context.new_page()
        page.add_init_script(_READY_PARTS)
        t0 = time.perf_counter()
        page.goto(url)
        page.wait_for_function(
            "window.explore && window.explore.state.info && window.explore.state.info.tables "
            "!== 'loading' && window.explore.state.previewX && window.explore.state.map",
            timeout=300000,
        )
        report["tables_ready_s"] = time.perf_counter() - t0
        report["ready_parts_s"] = page.evaluate("window.__ready")
        latent = np.array(page.evaluate("window.explore.state.info.latent"))
        box = page.locator("#map").bounding_box()
        ext = page.evaluate("window.explore.state.map.extent")

        def at(x):
            return (
                box["x"] + (x[0] - ext[0]) / (ext[1] - ext[0]) * box["width"],
                box["y"] + (1 - (x[1] - ext[2]) / (ext[3] - ext[2])) * box["height"],
            )

        report["settle_s"] = _settle(proc.pid)  # per-move CPU without the server's start-up work
        report["load_average_settled"] = os.getloadavg()
        cpu0 = _cpu_seconds(proc.pid)
        d = _drags(page, at, latent, drags, moves, pace_ms, driver=driver)
        report["cpu_ms_per_move"] = _cpu_per_move(cpu0, _cpu_seconds(proc.pid), d["moves"])
        per_move = report["cpu_ms_per_move"]
        report["cpu_ms_per_image"] = (
            {k: v * d["moves"] / d["images"] for k, v in per_move.items()}
            if per_move and d["images"]
            else None
        )
        report["load_average_after_drags"] = os.getloadavg()
        report["with_reference"] = (
            _with_reference(page, at, latent, drags, moves, pace_ms, driver) if reference else None
        )
        context.close()
    finally:
        launch.stop(proc)
    parts = d["parts"]
    report.update(
        {
            "move_to_frame_ms": _stats(d["latencies"] or [0]),
            "moves": d["moves"],
            "images": d["images"],
            **_rates(d),
            "delivery": d["delivery"],
            # where a frame's time goes: the server's blend + tonemap + encode, and send to answer
            "frame_server_ms": _stats([p[0] for p in parts] or [0]),
            "frame_round_trip_ms": _stats([p[1] for p in parts] or [0]),
            "sphere_draws": d["draws"],
            "load_average_after": os.getloadavg(),
        }
    )
    m, t = report["move_to_frame_ms"], BROWSER_TARGETS
    ref = report["with_reference"]
    report["meets_targets"] = {
        "median": m["median"] <= t["median_ms"],
        "p90": m["p90"] <= t["p90_ms"],
        "images_per_s": (report["images_per_s"] or 0) >= t["images_per_s"],
        "tables_ready": report["tables_ready_s"] <= t["tables_ready_s"],
        "rate_with_reference": None
        if ref is None
        else (ref["images_per_s"] or 0) >= t["rate_with_reference"] * (report["images_per_s"] or 0),
    }
    return report


#: Viewports of the screenshots beside the main one (``<stem>_<width>.png``).
SHOT_SIZES = ((800, 600), (1280, 800), (1600, 1000), (1920, 1080))


def _scenario(page, reference_spp, zoom_steps):
    """What the screenshots show: a path between a material near the centre of the data and its
    5th-nearest latent neighbour (the default kind, computed), scrubbed to t = 0.4; both ends and the point
    compared; the first end a favourite; the lobe plot; the thumbnails; a reference render
    (``reference_spp``, None: none); the map zoomed in on the path.
    """
    page.wait_for_function(
        "window.explore && window.explore.state.displayed && window.explore.state.map && "
        "window.explore.state.info.tables !== 'loading' && window.explore.state.previewX",
        timeout=300000,
    )
    latent = np.array(page.evaluate("window.explore.state.info.latent"))
    a = int(np.argmin(((latent - latent.mean(axis=0)) ** 2).sum(axis=1)))
    d = ((latent - latent[a]) ** 2).sum(axis=1)
    b = int(
        np.argsort(d)[min(5, len(d) - 1)]
    )  # the 5th nearest: a path long enough to see on the map
    for index, button in ((a, "#set-a"), (b, "#set-b")):
        page.evaluate(f"window.explore.setX(window.explore.state.info.latent[{index}])")
        page.wait_for_timeout(400)
        page.click(button)
        page.click("#compare-add")
        if index == a:
            page.click("#fav")
    page.wait_for_function(
        "window.explore.state.route.kind !== 'straight' || "
        "document.getElementById('route-state').textContent.includes('unavailable')",
        timeout=300000,
    )
    page.fill("#scrub", "400")
    page.dispatch_event("#scrub", "input")
    page.wait_for_timeout(800)
    page.click("#compare-add")
    page.click(".tabs button[data-tab=lobe]")
    xy = page.evaluate("""() => { const s = window.explore.state, c = document.getElementById('map');
        const r = c.getBoundingClientRect(), [x0, x1, y0, y1] = s.map.extent;
        return [r.left + (s.x[s.dims[0]] - x0) / (x1 - x0) * r.width,
                r.top + (1 - (s.x[s.dims[1]] - y0) / (y1 - y0)) * r.height]; }""")
    page.mouse.move(*xy)
    for _ in range(zoom_steps):
        page.mouse.wheel(0, -100)
        page.wait_for_timeout(120)
    box = page.locator("#map").bounding_box()
    page.mouse.move(box["x"] + box["width"] + 40, box["y"])
    page.dispatch_event("#map", "pointerleave")  # no tooltip left over the map
    if reference_spp and page.is_enabled("#ref-start"):  # the basis's scene is there
        page.select_option("#ref-spp", str(reference_spp))
        page.click("#ref-start")
        page.wait_for_selector("#ref-result:not([hidden])", timeout=600000)
        page.dispatch_event("#exposure", "input")  # a frame timed without the render beside it
    page.wait_for_function(
        "!window.explore.state.info.thumbs || window.explore.state.info.thumbs.state !== 'rendering'",
        timeout=600000,
    )
    page.wait_for_timeout(1500)


def screenshot(basis, path, manifold=None, reference_spp=256, size=(1560, 1000), zoom_steps=3):
    """PNG of the page (system Chromium through Playwright) at ``size``, with a reference render
    (:func:`_scenario`), and beside it ``<stem>_<width>.png`` at each of :data:`SHOT_SIZES`
    (the viewport, without the reference render).

    Returns ``path``, or None when Chromium or Playwright is missing.
    """
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return None
    if launch.find_chromium() is None:
        return None
    from mitsuba_manifold._util.atomic import write_bytes

    proc, url = launch.start([basis], manifold)
    try:
        with sync_playwright() as p:
            browser = _launch_chromium(p)
            for k, (w, h) in enumerate([size] + list(SHOT_SIZES)):
                context = browser.new_context(viewport={"width": w, "height": h})
                page = context.new_page()
                page.goto(url)
                _scenario(page, reference_spp if k == 0 else None, zoom_steps)
                out = path if k == 0 else f"{os.path.splitext(path)[0]}_{w}.png"
                page.evaluate("window.scrollTo(0, 0)")  # the clicks scrolled a small viewport
                page.wait_for_timeout(300)
                write_bytes(out, page.screenshot(full_page=k == 0))
                context.close()
            browser.close()
    finally:
        launch.stop(proc)
    return path


def fireflies(basis, manifold, out, points=12, seed=0):
    """Drag frames against rest frames of the explorer (:mod:`mitsuba_manifold.apps.explore.fireflies`):
    at the point 80% of the way from gold-metallic-paint (when the basis has it, else the first
    material) to its nearest latent neighbour, ``points - 1`` random points between pairs of
    materials and three materials, the summed blend (a drag's frame before the clamp), the drag's
    frame and the rest frame (L2+ denoised), in 8-bit sRGB. Writes ``out`` (PNG: 32x32 crops,
    x6, around the largest difference of the summed blend at the first two points; columns: drag
    frame without the clamp, with it, rest frame) and returns the worst mean, 99.9th percentile
    and largest difference to the rest frame over the points, without and with the clamp.
    """
    import io

    from PIL import Image, ImageDraw

    from mitsuba_manifold._util.atomic import write_bytes
    from mitsuba_manifold.apps.explore import encode
    from mitsuba_manifold.apps.explore import fireflies as ff
    from mitsuba_manifold.basis.blend import blend
    from mitsuba_manifold.basis.composition import compose
    from mitsuba_manifold.basis.folder import Basis
    from mitsuba_manifold.manifold.model import Manifold

    b = Basis.load(basis)
    m = Manifold.load(manifold or b.manifest.manifold)
    lat, rng = m.latent, np.random.default_rng(seed)
    first = m.index("gold-metallic-paint") if "gold-metallic-paint" in m.names else 0
    near = int(np.argsort(np.linalg.norm(lat - lat[first], axis=1))[1])
    xs = [0.8 * lat[first] + 0.2 * lat[near]]
    for _ in range(points - 1):
        i, j = rng.choice(len(lat), 2, replace=False)
        t = rng.uniform(0.2, 0.8)
        xs.append((1 - t) * lat[i] + t * lat[j])
    xs += [lat[k] for k in rng.choice(len(lat), 3, replace=False)]
    worst = {"summed": np.zeros(3), "clamped": np.zeros(3)}
    crops = []
    for k, x in enumerate(xs):
        raw, info = blend(b, m, x=x, l2="raw")
        l1 = compose(b, info.plan.keys, info.plan.image_weights, None)[0]
        drag, _ = ff.drag_image(raw, l1)
        rest, _ = blend(b, m, x=x, l2="denoised")
        s, d, r = (encode.tonemap(v, 0).astype(int) for v in (raw, drag, rest))
        for name, v in (("summed", s), ("clamped", d)):
            diff = np.abs(v - r)
            got = [diff.mean(), np.percentile(diff.max(axis=2), 99.9), diff.max()]
            worst[name] = np.maximum(worst[name], got)
        if k < 2:
            y, xx = np.unravel_index(np.abs(s - r).max(axis=2).argmax(), s.shape[:2])
            y0 = min(max(y - 16, 0), s.shape[0] - 32)
            x0 = min(max(xx - 16, 0), s.shape[1] - 32)
            crops.append(
                [
                    Image.fromarray(v[y0 : y0 + 32, x0 : x0 + 32].astype(np.uint8)).resize(
                        (192, 192), Image.NEAREST
                    )
                    for v in (s, d, r)
                ]
            )
    sheet = Image.new("RGB", (3 * 196, len(crops) * 196 + 18), "white")
    draw = ImageDraw.Draw(sheet)
    for c, label in enumerate(("drag frame, summed", "drag frame, clamped", "rest frame")):
        draw.text((c * 196 + 4, len(crops) * 196 + 4), label, fill="black")
    for r, row in enumerate(crops):
        for c, tile in enumerate(row):
            sheet.paste(tile, (c * 196, r * 196))
    buf = io.BytesIO()
    sheet.save(buf, format="PNG")
    write_bytes(out, buf.getvalue())
    return {
        "points": len(xs),
        "against the rest frame, 8-bit sRGB, worst over the points": {
            name: {"mean": float(v[0]), "p99_9": float(v[1]), "max": float(v[2])}
            for name, v in worst.items()
        },
        "crops": out,
    }
