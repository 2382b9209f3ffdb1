"""The explorer's background workers outlive their requests: a path, reference or refinement
whose page went away, that was cancelled or that failed never stops the worker, and the next
job of each kind completes."""

import json
import os
import time

import numpy as np
import pytest

pytest.importorskip("mitsuba")
pytest.importorskip("starlette")
pytestmark = pytest.mark.render

import test_explore  # noqa: E402

from mitsuba_manifold.apps.explore import reference  # noqa: E402
from mitsuba_manifold.errors import InputError  # noqa: E402
from mitsuba_manifold.manifold import paths  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402

small_basis, explorer, client = test_explore.small_basis, test_explore.explorer, test_explore.client


def _wait(job, timeout=120):
    deadline = time.monotonic() + timeout
    while job.state in ("queued", "rendering") and time.monotonic() < deadline:
        time.sleep(0.05)
    return job.state


def _ends(small_manifold_paper, i, j):
    m = Manifold.load(small_manifold_paper)
    return m.latent[i].tolist(), m.latent[j].tolist()


def test_a_tab_closed_while_its_path_computes_leaves_the_path_worker_running(
    client, explorer, small_manifold_paper
):
    """A page asks for a geodesic and goes away at once; a later path still completes (a
    cancelled request used to end the path thread for good)."""
    walks = explorer.walks
    for k in range(3):  # several pages leaving mid-path, the path queued or computing
        a, b = _ends(small_manifold_paper, k, k + 3)
        with client.websocket_connect(
            f"/ws?tab=gone{k}", headers={"origin": test_explore.TEST_ORIGIN}
        ) as ws:
            ws.send_text(
                json.dumps(
                    {"type": "route", "seq": 1, "a": a, "b": b, "kind": "geodesic", "steps": 9}
                )
            )
            time.sleep(0.05 * k)
    deadline = time.monotonic() + 60
    while walks.waiting() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert walks._thread.is_alive()
    a, b = _ends(small_manifold_paper, 1, 6)
    future = walks.submit(np.array(a), np.array(b), 7, "geodesic")
    try:
        route = future.result(timeout=60)
    finally:
        walks.release(future)
    assert len(route["points"]) == 7 and np.allclose(route["points"][0], a)


def test_a_released_path_never_starts_and_a_failed_one_does_not_stop_the_worker(
    explorer, small_manifold_paper, monkeypatch
):
    walks = explorer.walks
    real = paths.path
    calls = []

    def failing(manifold, a, b, steps, kind, metric=None):
        calls.append(steps)
        if steps == 5:
            raise FloatingPointError("boom")
        return real(manifold, a, b, steps, kind, metric=metric)

    monkeypatch.setattr(paths, "path", failing)
    a, b = (np.array(v) for v in _ends(small_manifold_paper, 2, 5))
    bad = walks.submit(a, b, 5, "uniform")
    with pytest.raises(InputError, match="uniform path failed"):
        bad.result(timeout=60)
    walks.release(bad)
    gone = walks.submit(a, b, 6, "uniform")
    walks.release(
        gone
    )  # nobody waits: cancelled before the worker takes it, or computed and cached
    good = walks.submit(a, b, 8, "uniform")
    assert len(good.result(timeout=60)["points"]) == 8
    walks.release(good)
    assert 6 not in calls or gone.done() and not gone.cancelled()
    assert walks._thread.is_alive()


def test_cancelled_and_abandoned_renders_stop_and_the_next_ones_complete(
    client, explorer, small_manifold_paper
):
    """A reference and a refinement cancelled by their page, and ones whose page went away,
    end as "cancelled"; the next reference and refinement then complete."""
    m = Manifold.load(small_manifold_paper)
    origin = {"origin": test_explore.TEST_ORIGIN}
    big = client.post(
        "/api/reference", json={"x": m.latent[0].tolist(), "spp": 4096}, headers=origin
    ).json()
    queued = client.post(
        "/api/reference", json={"x": m.latent[1].tolist(), "spp": 4096}, headers=origin
    ).json()
    for job in (queued, big):
        assert client.post(f"/api/reference/{job['id']}/cancel", headers=origin).status_code == 200
    with client.websocket_connect("/ws?tab=closing", headers=origin) as ws:
        ws.send_text(json.dumps({"type": "frame", "seq": 1, "x": m.latent[2].tolist()}))
        ws.receive_bytes()
        ref = client.post(
            "/api/reference",
            json={"x": m.latent[2].tolist(), "spp": 4096, "tab": "closing"},
            headers=origin,
        ).json()
        refine = client.post(
            "/api/reference",
            json={
                "x": (0.5 * (m.latent[2] + m.latent[3])).tolist(),
                "spp": 4096,
                "kind": "refine",
                "tab": "closing",
            },
            headers=origin,
        ).json()
    for job in (big, queued, ref, refine):
        assert _wait(explorer.references.get(job["id"]), 60) == "cancelled", job
    assert explorer.references.get(queued["id"]).seconds == 0.0  # never started
    done = explorer.start_reference(None, m.latent[4], 2)
    assert _wait(done) == "done", done.message
    refined = explorer.start_refine(None, 0.5 * (m.latent[4] + m.latent[5]), 2)
    assert _wait(refined) == "done", refined.message
    assert set(refined.images) == {"blend", "refined"}


def test_unknown_or_bad_tab_and_job_are_refused(client, small_manifold_paper):
    m = Manifold.load(small_manifold_paper)
    origin = {"origin": test_explore.TEST_ORIGIN}
    r = client.post(
        "/api/reference",
        json={"x": m.latent[0].tolist(), "spp": 2, "tab": "x" * 65},
        headers=origin,
    )
    assert r.status_code == 400 and "tab must be" in r.json()["error"]
    r = client.post("/api/reference/r999999/cancel", headers=origin)
    assert r.status_code == 400 and "unknown reference job" in r.json()["error"]


def test_snippets_name_the_manifold_relatively_and_render_after_the_folder_moves(
    explorer, small_manifold_paper, tmp_path
):
    """The copied XML names the manifold through $manifold, relative to the chosen scene folder;
    the scene and the manifold moved together to another folder render the same image, and the
    load_dict snippet loads the same material from its own folder."""
    import shutil

    import mitsuba as mi

    import mitsuba_manifold

    m = Manifold.load(small_manifold_paper)
    x = 0.5 * (m.latent[1] + m.latent[2])
    project = tmp_path / "project"
    (project / "scenes").mkdir(parents=True)
    (project / "data").mkdir()
    shutil.copy(small_manifold_paper, project / "data" / "manifold.npz")
    ex = explorer
    saved, ex.manifold_path = ex.manifold_path, str(project / "data" / "manifold.npz")
    try:
        sn = ex.snippets(x, str(project / "scenes"))
    finally:
        ex.manifold_path = saved
    assert str(tmp_path) not in sn["xml"] and str(tmp_path) not in sn["python"]
    assert sn["manifold"] == "../data/manifold.npz" and 'value="$manifold"' in sn["xml"]
    scene = f"""<scene version="3.0.0"><integrator type="path"/>{sn["xml"]}
        <shape type="sphere"><ref id="material"/></shape>
        <emitter type="constant"><rgb name="radiance" value="1"/></emitter>
        <sensor type="perspective"><transform name="to_world"><lookat origin="0,0,4" target="0,0,0" up="0,1,0"/>
        </transform><film type="hdrfilm"><integer name="width" value="12"/><integer name="height" value="12"/></film>
        <sampler type="independent"><integer name="sample_count" value="2"/></sampler></sensor></scene>"""
    (project / "scenes" / "s.xml").write_text(scene)
    (project / "scenes" / "s.py").write_text(sn["python"])
    mi.set_variant("llvm_ad_rgb")
    mitsuba_manifold.register()
    before = np.array(mi.render(mi.load_file(str(project / "scenes" / "s.xml")), seed=1))
    moved = tmp_path / "elsewhere" / "moved"
    shutil.move(str(project), str(moved))
    after = np.array(mi.render(mi.load_file(str(moved / "scenes" / "s.xml")), seed=1))
    assert np.isfinite(after).all() and after.mean() > 0
    # Mitsuba's default (Gaussian) film filter splats each sample into neighbouring pixels from
    # parallel threads, so the two renders may differ in the summation order: 1 ulp, not a material.
    np.testing.assert_allclose(after, before, rtol=1e-5, atol=1e-6)
    namespace = {"__file__": str(moved / "scenes" / "s.py")}
    exec(compile(sn["python"], "s.py", "exec"), namespace)
    np.testing.assert_allclose(namespace["bsdf"].latent, x, rtol=1e-5)
    with pytest.raises(InputError, match="absolute folder"):
        explorer.snippets(x, "relative/folder")


def _process_state(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0]  # R, S, T (stopped), ...
    except FileNotFoundError:
        return "ended"


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads process states from /proc")
def test_a_drag_pauses_a_running_reference_and_it_completes_after(
    client, explorer, small_manifold_paper, monkeypatch
):
    """The frames of a drag pause a running reference render (its process stopped while they
    come, so it takes none of their CPU), which goes on by itself once they stop and completes."""
    monkeypatch.setattr(reference, "HOLD_S", 2.0)  # longer than a frame takes on a loaded machine
    m = Manifold.load(small_manifold_paper)
    job = explorer.start_reference(None, m.latent[0], 4096)
    deadline = time.monotonic() + 60
    while job.process is None and job.state in ("queued", "rendering"):
        assert time.monotonic() < deadline, "the reference render did not start"
        time.sleep(0.02)
    pid = job.process.pid
    origin = {"origin": test_explore.TEST_ORIGIN}
    with client.websocket_connect("/ws", headers=origin) as ws:

        def drag_frame(seq):
            x = (0.5 * (m.latent[1] + m.latent[2]) + 0.001 * seq).tolist()
            ws.send_text(json.dumps({"type": "frame", "seq": seq, "x": x, "coarse": True}))
            ws.receive_bytes()

        seq, deadline = 1, time.monotonic() + 30
        drag_frame(seq)
        while _process_state(pid) != "T":  # stopped while the drag runs
            assert time.monotonic() < deadline, "a drag's frames did not pause the render"
            seq += 1
            drag_frame(seq)
        progress = job.progress
        for _ in range(3):  # the drag goes on: the render stays paused
            seq += 1
            drag_frame(seq)
            time.sleep(0.1)
            assert _process_state(pid) == "T" and job.progress == progress
    deadline = time.monotonic() + 5 * reference.HOLD_S
    while job.process is not None and _process_state(pid) == "T":
        assert time.monotonic() < deadline, "the render was not resumed after the drag"
        time.sleep(0.02)
    assert _wait(job) == "done", job.message
    assert not explorer.references._paused


def test_a_path_reports_progress_and_the_page_can_cancel_it(
    client, explorer, small_manifold_paper, monkeypatch
):
    """A slow path sends its progress to the page while it is computed; the page's cancel
    answers the route with "cancelled" and stops the path at its next step."""
    walks = explorer.walks
    steps_done = []

    def slow(manifold, a, b, steps, kind, metric=None):  # 200 evaluations of 0.05 s: 10 s
        X = paths.straight(np.asarray(a), np.asarray(b), steps)
        for k in range(200):
            metric.features(X)
            steps_done.append(k)
            time.sleep(0.05)
        return X

    monkeypatch.setattr(paths, "path", slow)
    a, b = _ends(small_manifold_paper, 0, 5)
    b = [v + 0.0123 for v in b]  # ends no earlier test has cached
    with client.websocket_connect(
        "/ws?tab=canceller", headers={"origin": test_explore.TEST_ORIGIN}
    ) as ws:
        ws.send_text(
            json.dumps({"type": "route", "seq": 7, "a": a, "b": b, "kind": "geodesic", "steps": 9})
        )
        progress = []
        while len(progress) < 2:
            meta, _ = test_explore._unpack(ws.receive_bytes())
            assert meta["type"] == "progress", meta
            progress.append(meta)
        assert progress[0]["kind"] == "route" and progress[0]["route_seq"] == 7
        assert 0 < progress[0]["evaluations"] < progress[1]["evaluations"]
        assert 0 < progress[0]["seconds"] < progress[1]["seconds"]
        ws.send_text(json.dumps({"type": "cancel", "kind": "route"}))
        while True:
            meta, _ = test_explore._unpack(ws.receive_bytes())
            if meta["type"] != "progress":
                break
        assert meta["type"] == "error" and meta["kind"] == "route" and meta["seq"] == 7, meta
        assert "cancelled" in meta["error"]
    deadline = time.monotonic() + 30
    while walks.waiting() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not walks.waiting() and len(steps_done) < 200  # stopped long before its end
    assert walks._thread.is_alive()


def test_the_path_thread_runs_at_the_servers_own_priority(explorer):
    """Not niced: on a busy machine a lowered priority starved the paths for minutes."""
    walks = explorer.walks
    assert os.getpriority(os.PRIO_PROCESS, walks._thread.native_id) == os.getpriority(
        os.PRIO_PROCESS, 0
    )
