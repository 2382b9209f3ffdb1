"""The explorer's reference jobs are bounded and leave nothing behind: each page has a few jobs
waiting at most (a clear refusal beyond), and a job that fails, is cancelled or completes
removes its temporary folder."""

import glob
import os
import tempfile
import time

import pytest

pytest.importorskip("mitsuba")
pytest.importorskip("starlette")
pytestmark = pytest.mark.render

import test_explore  # noqa: E402

from mitsuba_manifold.apps.explore import reference  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402

small_basis, explorer, client = test_explore.small_basis, test_explore.explorer, test_explore.client
ORIGIN = {"origin": test_explore.TEST_ORIGIN}


def _wait(job, timeout=120):
    deadline = time.monotonic() + timeout
    while job.state in ("queued", "rendering") and time.monotonic() < deadline:
        time.sleep(0.05)
    return job.state


@pytest.fixture
def temp_here(tmp_path, monkeypatch):
    """The temporary folders of this test under ``tmp_path`` (tempfile's default folder)."""
    folder = tmp_path / "tmp"
    folder.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(folder))
    return folder


def test_failed_cancelled_and_done_jobs_leave_no_temporary_folder(
    explorer, small_manifold_paper, temp_here, tmp_path, monkeypatch
):
    m = Manifold.load(small_manifold_paper)
    name = next(iter(explorer.bases))
    broken = tmp_path / "broken.xml"
    broken.write_text("<scene version='3.0.0'><shape type='nonexistent_plugin'/></scene>")
    monkeypatch.setitem(explorer.scenes, name, str(broken))
    failed = explorer.start_reference(None, m.latent[0], 4)
    assert _wait(failed) == "failed" and failed.message, failed.status()
    monkeypatch.undo()
    monkeypatch.setattr(tempfile, "tempdir", str(temp_here))
    cancelled = explorer.start_reference(None, m.latent[1], 1 << 14)
    deadline = time.monotonic() + 60
    while cancelled.state != "rendering" and time.monotonic() < deadline:
        time.sleep(0.02)
    explorer.references.cancel(cancelled.id)
    assert _wait(cancelled) == "cancelled"
    done = explorer.start_reference(None, m.latent[2], 2)
    assert _wait(done) == "done", done.message
    # the explorer's folder of renders stays while it runs (shutdown removes it), empty
    assert len(glob.glob(os.path.join(temp_here, "explore-reference-*"))) == 1
    assert glob.glob(os.path.join(temp_here, "explore-reference-*", "*")) == []


def test_a_page_has_a_few_jobs_waiting_at_most_and_a_clear_refusal_beyond(
    client, explorer, small_manifold_paper
):
    m = Manifold.load(small_manifold_paper)
    ids = []
    try:
        for k in range(reference.MAX_WAITING_PER_TAB):
            r = client.post(
                "/api/reference",
                json={"x": m.latent[k % m.n].tolist(), "spp": 1 << 14, "tab": "busy"},
                headers=ORIGIN,
            )
            assert r.status_code == 200, r.text
            ids.append(r.json()["id"])
        refused = client.post(
            "/api/reference",
            json={"x": m.latent[0].tolist(), "spp": 4, "tab": "busy"},
            headers=ORIGIN,
        )
        assert (
            refused.status_code == 429
            and "this page has 4 renders waiting" in refused.json()["error"]
        ), refused.text
        other = client.post(  # another page is not held up by this one's queue
            "/api/reference",
            json={"x": m.latent[0].tolist(), "spp": 4, "tab": "calm"},
            headers=ORIGIN,
        )
        assert other.status_code == 200, other.text
        ids.append(other.json()["id"])
        client.post(f"/api/reference/{ids[1]}/cancel", headers=ORIGIN)
        again = client.post(  # one cancelled: room again
            "/api/reference",
            json={"x": m.latent[0].tolist(), "spp": 4, "tab": "busy"},
            headers=ORIGIN,
        )
        assert again.status_code == 200, again.text
        ids.append(again.json()["id"])
        for _ in range(3 * reference.MAX_WAITING_PER_TAB):  # refinements supersede each other
            r = client.post(
                "/api/reference",
                json={"x": m.latent[1].tolist(), "spp": 4, "kind": "refine", "tab": "refiner"},
                headers=ORIGIN,
            )
            assert r.status_code == 200, r.text
            ids.append(r.json()["id"])
    finally:
        for job_id in ids:
            explorer.references.cancel(job_id)
    for job_id in ids:  # (a finished job may be forgotten: KEEP_JOBS)
        job = explorer.references.get(job_id)
        assert job is None or _wait(job, 60) in ("cancelled", "done", "failed")


def test_a_stopping_server_removes_the_files_of_the_render_it_ends(
    explorer, small_manifold_paper, temp_here
):
    """Stopped while a reference renders (the CLI waits 0.3 s, then exits at once): its files
    are gone when shutdown returns."""
    m = Manifold.load(small_manifold_paper)
    refs = reference.References()
    name = next(iter(explorer.bases))
    basis = explorer.bases[name]
    job = refs.submit(
        name,
        basis,
        explorer.scenes[name],
        explorer.manifold_path,
        m.latent[0],
        1 << 14,
        explorer.blend(name, m.latent[0])[0],
    )
    deadline = time.monotonic() + 60
    while job.process is None and time.monotonic() < deadline:
        time.sleep(0.02)
    assert job.state == "rendering" and glob.glob(os.path.join(temp_here, "explore-reference-*"))
    refs.shutdown(wait=0.0)
    assert glob.glob(os.path.join(temp_here, "explore-reference-*")) == []
    _wait(job, 30)


def test_the_folders_of_a_killed_explorer_are_removed_when_the_next_one_starts(
    explorer, small_manifold_paper, temp_here
):
    import subprocess

    gone = subprocess.Popen(["true"])
    gone.wait()  # a process that no longer runs: its explorer was killed
    dead = temp_here / f"explore-reference-{gone.pid}-abcd"
    (dead / "job-1").mkdir(parents=True)
    (dead / "job-1" / "spec.json").write_text("{}")
    alive = temp_here / f"explore-reference-{os.getppid()}-efgh"  # an explorer still running
    alive.mkdir()
    other = temp_here / "explore-reference-notmine"
    other.mkdir()
    refs = reference.References()
    assert not dead.exists() and alive.exists() and other.exists()
    try:  # and its own folder is made and removed as before
        m = Manifold.load(small_manifold_paper)
        name = next(iter(explorer.bases))
        job = refs.submit(
            name,
            explorer.bases[name],
            explorer.scenes[name],
            explorer.manifold_path,
            m.latent[0],
            2,
            explorer.blend(name, m.latent[0])[0],
        )
        assert _wait(job) == "done", job.message
    finally:
        refs.shutdown(wait=5)
    assert not dead.exists() and alive.exists() and other.exists()
