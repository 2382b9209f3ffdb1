"""Chunked basis rendering: planning, merging, resuming, and the Ray executor."""

import os
import signal
import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from mitsuba_manifold import errors  # noqa: E402
from mitsuba_manifold.basis import folder as basis  # noqa: E402
from mitsuba_manifold.imaging import io as imageio  # noqa: E402
from mitsuba_manifold.render.jobs import chunks, executor, render_basis  # noqa: E402
from mitsuba_manifold.render.jobs.render_basis import (
    BasisOptions,
    FullGI,
    RunBehaviour,
    Sampling,
    SceneSetup,
    Selection,
)  # noqa: E402
from mitsuba_manifold.render.scene.scenes import scene_path  # noqa: E402

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]  # renders and starts Ray

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
SPHERE = scene_path("sphere")
RES = 16
OPTIONS = {
    "mode": "onepass",
    "resolution": RES,
    "materials": ["gold-paint", "chrome", "pink-fabric"],
}


def _images(folder):
    b = basis.Basis.load(folder)
    return {k: imageio.read_exr(b.path(k)) for k in ["base"] + b.keys}


def test_plan_splits_samples_and_seeds():
    specs = chunks.plan(SPHERE, SPHERE, 4, BasisOptions().updated(spp=10, seed=3, mode="onepass"))
    assert [s.spp for s in specs] == [3, 3, 2, 2]
    assert [s.seed for s in specs] == [12, 13, 14, 15]
    assert len({s.name for s in specs}) == 4
    with pytest.raises(errors.MismatchError, match="at least the number of chunks"):
        chunks.plan(SPHERE, SPHERE, 3, BasisOptions().updated(spp=2))
    with pytest.raises(errors.MismatchError, match="`chunks` must be >= 1"):
        chunks.plan(SPHERE, SPHERE, 0, BasisOptions().updated(spp=2))


#: Chunk keys computed by the keyword-dict planner for the options the command line passed
#: (``render_basis.py --chunks 2``), with the identities ``IDS``: a chunk saved by such a run
#: keeps its key.
IDS = ("a" * 64, "b" * 64)
CLI_KEYS = {
    "defaults": (
        BasisOptions(
            sampling=Sampling(spp=8, seed=0, mode="per-material"),
            gi=FullGI(components="l1"),
            run=RunBehaviour(progress=True),
        ),
        [
            "4184144e0a495a8aaf43729817c6e5d5b4f18f1bf7e0bb31feb7ecf6c4fa259e",
            "d419d82faa13566fba3ccab174ce563098183bb1f70fd2151ac1e48cfdb2a7e2",
        ],
    ),
    "every option set": (
        BasisOptions(
            selection=Selection(materials=["gold-paint", "chrome"], near=[0.1, -0.2], radius=0.5),
            sampling=Sampling(spp=9, seed=3, mode="onepass"),
            scene=SceneSetup(
                resolution=(32, 24),
                max_depth=5,
                variant="llvm_ad_rgb",
                x=[0.25, 0.5],
                database="db",
                sensor=1,
            ),
            gi=FullGI(components="full"),
            run=RunBehaviour(force=True, progress=True, aovs=True),
        ),
        [
            "e5be8189aa3315739b79e4b222b2278d3498b57fbed4039b531ad89eb0909f78",
            "0656fb42354a6e952bcda7ecb6622e406ac2a69b16c074ecb9074b0220536f26",
        ],
    ),
}


@pytest.mark.parametrize("case", list(CLI_KEYS))
def test_chunk_keys_of_the_command_line_are_those_of_chunks_saved_before(case):
    options, keys = CLI_KEYS[case]
    specs = chunks.plan("scene.xml", "m.npz", 2, options)
    assert [chunks.chunk_key(s, IDS) for s in specs] == keys


#: A value other than the default of every :class:`BasisOptions` field.
CHANGED = {
    "materials": ["chrome"],
    "near": [0.5, 0.5],
    "radius": 1.0,
    "spp": 65,
    "seed": 1,
    "mode": "onepass",
    "chunk_spp": 4,
    "resolution": 32,
    "max_depth": 3,
    "variant": "scalar_rgb",
    "x": [0.1, 0.2],
    "database": "elsewhere",
    "sensor": 2,
    "components": "full",
    "levels": 2,
    "cross_tol": 0.01,
    "cross_light_tol": 0.0,
    "cross_fraction": 0.5,
    "cross_keep": [("a", "b")],
    "force": True,
    "progress": True,
    "aovs": True,
}


def test_every_option_that_changes_the_images_changes_the_chunk_key():
    """No render option is left out of a chunk's key: each one changes it, but those that
    change no image (folder handling, progress, guides rendered after the merge, where the
    tables are)."""
    assert set(CHANGED) == set(BasisOptions().keywords())
    base = chunks.chunk_key(chunks.plan("s.xml", "m.npz", 1, BasisOptions())[0], IDS)
    for name, value in CHANGED.items():
        spec = chunks.plan("s.xml", "m.npz", 1, BasisOptions().updated(**{name: value}))[0]
        same = chunks.chunk_key(spec, IDS) == base
        assert same == (name in ("force", "progress", "aovs", "database")), name
        assert spec.options.keywords()[name] == value  # the chunk renders with it


def test_a_misspelt_option_is_refused_before_the_folder_is_made(tmp_path, small_manifold):
    out = tmp_path / "basis"
    with pytest.raises(TypeError, match="resolutoin"):
        chunks.render_chunked(SPHERE, small_manifold, out, chunks=2, spp=4, resolutoin=RES)
    assert not out.exists()


def test_merged_chunks_equal_single_process_basis(tmp_path, small_manifold):
    """k chunks at S/k spp with seeds seed*k+j are the passes of one render at S spp."""
    single = tmp_path / "single"
    render_basis.render_basis(
        SPHERE, small_manifold, str(single), spp=8, seed=2, chunk_spp=2, **OPTIONS
    )
    run = chunks.render_chunked(
        SPHERE, small_manifold, str(tmp_path / "merged"), spp=8, chunks=4, seed=2, **OPTIONS
    )
    assert run.manifest.spp == 8 and run.manifest.chunks == 4 and len(run.rendered) == 4
    a, b = _images(single), _images(tmp_path / "merged")
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_allclose(b[k], a[k], rtol=2e-6, atol=1e-7 * max(1.0, float(a[k].max())))
    assert not (tmp_path / "merged" / chunks.CHUNK_DIR).exists()
    # a different seed gives different images (the comparison above can fail)
    other = chunks.render_chunked(
        SPHERE, small_manifold, str(tmp_path / "other"), spp=8, chunks=4, seed=5, **OPTIONS
    )
    assert other.manifest.seed == 5
    assert not np.allclose(_images(tmp_path / "other")["chrome"], b["chrome"])


def test_resume_per_chunk_and_refusals(tmp_path, small_manifold):
    out = tmp_path / "b"

    class Dies(executor.LocalExecutor):
        """Renders two chunks, then the run is killed."""

        def map(self, fn, items):
            for i, item in enumerate(items):
                if i == 2:
                    raise KeyboardInterrupt
                yield fn(item)

    with pytest.raises(KeyboardInterrupt):
        chunks.render_chunked(
            SPHERE, small_manifold, str(out), spp=4, chunks=4, executor=Dies(), **OPTIONS
        )
    done = sorted(os.listdir(out / chunks.CHUNK_DIR))
    assert done == ["000-of-004", "001-of-004"]
    run = chunks.render_chunked(
        SPHERE, small_manifold, str(out), spp=4, chunks=4, keep_chunks=True, **OPTIONS
    )
    assert run.resumed == done and [r[0] for r in run.rendered] == ["002-of-004", "003-of-004"]
    ref = chunks.render_chunked(
        SPHERE, small_manifold, str(tmp_path / "ref"), spp=4, chunks=4, **OPTIONS
    )
    for k, img in _images(out).items():
        np.testing.assert_array_equal(img, _images(tmp_path / "ref")[k])
    assert ref.manifest.images.keys() == run.manifest.images.keys()
    before = {f: os.path.getmtime(out / f) for f in os.listdir(out) if f.endswith(".exr")}
    with pytest.raises(errors.InputError, match="other settings .*spp"):
        chunks.render_chunked(SPHERE, small_manifold, str(out), spp=8, chunks=4, **OPTIONS)
    with pytest.raises(
        errors.InputError, match="other settings"
    ):  # one-process render into a merged basis
        render_basis.render_basis(SPHERE, small_manifold, str(out), spp=4, **OPTIONS)
    assert before == {f: os.path.getmtime(out / f) for f in os.listdir(out) if f.endswith(".exr")}
    # the same command again: nothing to render, nothing refused, nothing rewritten
    again = chunks.render_chunked(SPHERE, small_manifold, str(out), spp=4, chunks=4, **OPTIONS)
    assert again.manifest.images.keys() == run.manifest.images.keys()
    assert before == {f: os.path.getmtime(out / f) for f in os.listdir(out) if f.endswith(".exr")}


@pytest.mark.parametrize("after", [1, 3])
def test_an_interrupted_merge_resumes_with_the_same_command(
    tmp_path, small_manifold, monkeypatch, after
):
    """Ctrl-C while the merge writes its images: the same command then completes the basis (no
    "files this basis did not make"), equal to an uninterrupted run."""
    out = tmp_path / "b"
    write, merged = imageio.write_exr, []

    def interrupted(path, img, *a, **k):  # the merge's writes are the ones into `out` itself
        if os.path.dirname(os.fspath(path)) == str(out):
            merged.append(path)
            if len(merged) > after:
                raise KeyboardInterrupt
        return write(path, img, *a, **k)

    monkeypatch.setattr(chunks.imageio, "write_exr", interrupted)
    with pytest.raises(KeyboardInterrupt):
        chunks.render_chunked(SPHERE, small_manifold, str(out), spp=2, chunks=2, **OPTIONS)
    monkeypatch.setattr(chunks.imageio, "write_exr", write)
    run = chunks.render_chunked(SPHERE, small_manifold, str(out), spp=2, chunks=2, **OPTIONS)
    assert run.resumed == ["000-of-002", "001-of-002"] and run.manifest.pending is None
    chunks.render_chunked(SPHERE, small_manifold, str(tmp_path / "ref"), spp=2, chunks=2, **OPTIONS)
    mine, theirs = _images(out), _images(tmp_path / "ref")
    assert mine.keys() == theirs.keys()
    for k in mine:
        np.testing.assert_array_equal(mine[k], theirs[k])


def test_chunked_basis_with_denoising_guides(tmp_path, small_manifold):
    from mitsuba_manifold.basis import denoise

    out = tmp_path / "aov"
    run = chunks.render_chunked(
        SPHERE, small_manifold, str(out), spp=2, chunks=2, aovs=True, **OPTIONS
    )
    assert denoise.BasisAOVs.load(str(out), run.manifest) is not None


def test_cli_chunks_views_and_scenes(tmp_path, small_manifold):
    scene2 = tmp_path / "two_views.xml"
    text = open(SPHERE).read()
    # a second sensor: the same camera (so both views must match) as another view
    start = text.index("<sensor")
    end = text.index("</sensor>") + len("</sensor>")
    scene2.write_text(text[:end] + text[start:end] + text[end:])
    os.symlink(os.path.join(os.path.dirname(SPHERE), "sky.exr"), tmp_path / "sky.exr")
    r = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "tools", "render_basis.py"),
            SPHERE,
            str(scene2),
            "--manifold",
            small_manifold,
            "--out",
            str(tmp_path / "out"),
            "--views",
            "all",
            "--chunks",
            "2",
            "--spp",
            "2",
            "--res",
            str(RES),
            "--materials",
            "gold-paint,chrome",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    folders = sorted(os.listdir(tmp_path / "out"))
    assert folders == ["sphere", "two_views-view0", "two_views-view1"]
    v0, v1 = (
        _images(tmp_path / "out" / "two_views-view0"),
        _images(tmp_path / "out" / "two_views-view1"),
    )
    assert basis.Manifest.read(tmp_path / "out" / "two_views-view1").sensor == 1
    np.testing.assert_allclose(v0["chrome"], v1["chrome"], rtol=1e-5, atol=1e-6)
    r = subprocess.run(
        [
            sys.executable,
            os.path.join(ROOT, "tools", "render_basis.py"),
            SPHERE,
            "--manifold",
            small_manifold,
            "--out",
            str(tmp_path / "bad"),
            "--views",
            "3",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 2 and "sensor 3" in r.stderr and "1 sensor" in r.stderr


# ------------------------------------------------------------------------------- Ray


def _die_once(job):
    """Kill this worker process the first time any chunk runs (marker file), then render."""
    marker, spec = job
    if not os.path.exists(marker):
        with open(marker, "w") as f:
            f.write(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGKILL)
    return chunks.render_chunk(spec)


@pytest.fixture(scope="module")
def ray_cluster():
    ray = pytest.importorskip("ray")
    # workers import the package from this tree, and this module (for _die_once) by name
    path = os.pathsep.join(
        [ROOT, os.path.dirname(os.path.abspath(__file__)), os.environ.get("PYTHONPATH", "")]
    )
    ray.init(
        num_cpus=2,
        include_dashboard=False,
        log_to_driver=False,
        runtime_env={"env_vars": {"PYTHONPATH": path}},
    )
    yield ray
    ray.shutdown()


def test_ray_chunks_equal_local_chunks_and_killed_worker_reruns(
    tmp_path, small_manifold, ray_cluster
):
    local = chunks.render_chunked(
        SPHERE, small_manifold, str(tmp_path / "local"), spp=4, chunks=2, seed=1, **OPTIONS
    )
    ray_ex = executor.RayExecutor(max_retries=2)
    run = chunks.render_chunked(
        SPHERE,
        small_manifold,
        str(tmp_path / "ray"),
        spp=4,
        chunks=2,
        seed=1,
        executor=ray_ex,
        **OPTIONS,
    )
    pids = {r[3] for r in run.rendered}
    assert os.getpid() not in pids
    a, b = _images(tmp_path / "local"), _images(tmp_path / "ray")
    for k in a:
        np.testing.assert_allclose(b[k], a[k], rtol=1e-6, atol=1e-7)
    assert local.manifest.images.keys() == run.manifest.images.keys()

    # a worker killed while rendering: Ray re-runs its task, the basis is complete and the same
    marker = tmp_path / "killed-once"
    specs = chunks.plan(SPHERE, small_manifold, 2, BasisOptions().updated(spp=4, seed=1, **OPTIONS))
    results = list(ray_ex.map(_die_once, [(str(marker), s) for s in specs]))
    assert marker.exists() and int(marker.read_text()) not in {r.pid for r in results}
    assert sorted(r.spec.name for r in results) == ["000-of-002", "001-of-002"]
    for r in results:
        chunks.save_chunk(str(tmp_path / "killed"), r)
    chunks.merge(
        str(tmp_path / "killed"),
        [chunks.chunk_folder(tmp_path / "killed", s) for s in specs],
        seed=1,
    )
    for k, img in _images(tmp_path / "killed").items():
        np.testing.assert_allclose(img, a[k], rtol=1e-6, atol=1e-7)
    # without retries the same fault fails the run
    marker.unlink()
    with pytest.raises(Exception, match="(?i)worker|died|crash|exit"):
        list(executor.RayExecutor(max_retries=0).map(_die_once, [(str(marker), specs[0])]))


def test_ray_missing_is_a_clear_error(monkeypatch):
    import builtins

    real = builtins.__import__

    def no_ray(name, *a, **k):
        if name == "ray":
            raise ImportError("no ray")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_ray)
    with pytest.raises(errors.UnavailableError, match="pip install"):
        list(executor.RayExecutor().map(len, ["a"]))
    with pytest.raises(errors.UnavailableError, match="`address` is for"):
        executor.make_executor("local", address="auto")


def test_merged_chunks_of_a_full_gi_basis_equal_the_single_process_one(tmp_path, small_manifold):
    """The table's full-GI images and cross terms merge as the L1- images do."""
    opts = dict(OPTIONS, materials="all", components="full")
    single = tmp_path / "single"
    render_basis.render_basis(
        scene_path("table"), small_manifold, str(single), spp=4, seed=1, chunk_spp=2, **opts
    )
    run = chunks.render_chunked(
        scene_path("table"),
        small_manifold,
        str(tmp_path / "merged"),
        spp=4,
        chunks=2,
        seed=1,
        **opts,
    )
    assert run.manifest.components == basis.Manifest.read(single).components
    assert "l2+" in run.manifest.components
    a, b = basis.Basis.load(single), basis.Basis.load(tmp_path / "merged")
    for k in a.keys:
        ref = a.image(a.gi_key(k))
        np.testing.assert_allclose(
            b.image(b.gi_key(k)), ref, rtol=2e-6, atol=1e-7 * max(1.0, float(ref.max()))
        )
    (pa, ca), (pb, cb) = a.cross_terms(), b.cross_terms()
    assert pa == pb
    np.testing.assert_allclose(
        cb, ca, rtol=2e-3, atol=1e-3 * max(1.0, float(np.abs(ca).max()))
    )  # float16


def test_components_auto_is_the_former_spelling_of_full_and_keeps_the_chunk_keys():
    """``FullGI(components="auto")`` warns, names ``'full'``, and keys chunks as before."""
    options, keys = CLI_KEYS["every option set"]
    with pytest.warns(DeprecationWarning, match="components='full'"):
        old = FullGI(components="auto")
    assert old == options.gi and old.components == "full"
    specs = chunks.plan("scene.xml", "m.npz", 2, replace(options, gi=old))
    assert [chunks.chunk_key(s, IDS) for s in specs] == keys


def test_a_chunk_mark_reads_as_written_and_a_damaged_one_is_no_mark():
    """The chunk bookkeeping is this module's (ChunkMark), kept by the manifest as keys it
    leaves to the jobs: written and read back the same, in the keys chunks saved before used."""
    data = {
        "format": "mitsuba-manifold-basis",
        "version": 2,
        "scene": "/s.xml",
        "scene_hash": "a" * 64,
        "manifold": "/m.npz",
        "manifold_hash": "b" * 64,
        "resolution": [4, 3],
        "spp": 4,
        "variant": "llvm_ad_rgb",
        "seed": 0,
        "max_depth": -1,
        "mode": "onepass",
        "targets": ["mat"],
        "images": {},
        "chunk_complete": True,
        "chunk_run": {"seconds": 1.5, "host": "h", "pid": 7},
        "chunk_key": "e" * 64,
    }
    m = basis.Manifest.from_json(data)
    mark = chunks.ChunkMark.of(m)
    assert (mark.chunk_complete, mark.chunk_run.host, mark.chunk_key) == (True, "h", "e" * 64)
    again = basis.Manifest.from_json({k: v for k, v in data.items() if not k.startswith("chunk_")})
    mark.put(again)
    assert again.to_json() == data
    chunks.ChunkMark().put(again)  # a merged basis is no chunk
    assert not any(k.startswith("chunk_") for k in again.to_json())
    damaged = basis.Manifest.from_json(dict(data, chunk_run={"seconds": "1.5"}))
    assert chunks.ChunkMark.of(damaged) == chunks.ChunkMark()  # rendered again, never trusted
