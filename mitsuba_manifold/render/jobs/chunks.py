"""A basis rendered in chunks of samples, then merged.

A basis image is a Monte Carlo mean over samples, so a basis at ``S`` spp is the
spp-weighted mean of ``k`` bases at ``S_j`` spp (``sum S_j = S``) rendered with different
seeds. Chunks are independent: :mod:`mitsuba_manifold.render.jobs.executor` runs them one after
another in this process (``local``) or as Ray tasks (``ray``), and :func:`render_chunked`
merges them into an ordinary basis folder (:mod:`mitsuba_manifold.basis.folder` format).

Seeds: chunk ``j`` of ``k`` is rendered with seed ``seed * k + j``. The one-pass renderer
seeds pass ``p`` of ``n`` with ``seed * n + p``, so when every chunk is one pass
(``S_j * pixels`` at most ``max_samples``, 4M), the merged basis equals the single-process
basis rendered with ``spp_per_pass = S / k`` and the same seed, to float32 rounding
(exactly the same samples, summed in another order). A full-GI basis chooses its cross
terms' pairs on its first pass (:class:`~.integrators.multisplats.PairSelection`): its first
chunk is rendered first and the others keep the pairs it chose (``cross_keep``), as the
single process's later passes do. With a box filter (the basis
scenes') every sample weighs 1 and the spp-weighted mean is exact; with other filters
it is an unbiased estimate of the same image, not the identical sum.

Resumable per chunk: the driver writes each finished chunk into
``<out>/.chunks/<j>-of-<k>/`` (images first, manifest last, every file atomically); a
chunk whose folder holds a complete manifest of the same settings (its ``chunk_key``:
:func:`chunk_key` of its index, count, spp, seed, options and the scene's and manifold's
identities) and unchanged images is not rendered again; a chunk of other settings is. The
merge writes ``<out>``'s images atomically and refuses a folder holding a basis of other
settings (the manifest records ``chunks``: ``k``); a merged basis records the key of the
whole run, so the same command on a finished basis renders nothing. Chunk folders are
removed after a merge unless ``keep_chunks``. The driver holds ``<out>``'s folder lock
(:class:`~mitsuba_manifold._util.locking.FolderLock`) from the first chunk to the merge: a
second run into the same folder is refused at once.
"""

import json
import os
import shutil
import socket
import tempfile
import time
from dataclasses import dataclass, replace
from typing import Optional

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from ..._util.cache import file_hash, key_hash
from ..._util.locking import FolderLock
from ...basis import folder as basis_folder
from ...basis.folder.output import CHUNK_DIR, check_foreign_folder, open_folder
from ...errors import MismatchError
from ...imaging import io as imageio
from .gi_basis import write_cross
from .render_basis import BasisOptions, ensure_aovs, render_basis


class ChunkRun(BaseModel):
    """Where and how fast a chunk was rendered (a chunk manifest's ``chunk_run``)."""

    model_config = ConfigDict(strict=True, frozen=True, extra="allow")

    seconds: float = Field(description="seconds the chunk's render took")
    host: str = Field(description="the machine that rendered it")
    pid: int = Field(description="the process that rendered it")


class ChunkMark(BaseModel):
    """The keys a chunked render adds to a basis manifest: the bookkeeping of this module,
    not of the basis format, which keeps them as they are (:attr:`Manifest.extra
    <mitsuba_manifold.basis.folder.Manifest>`).

    ``chunk_complete`` and ``chunk_run`` mark a chunk folder whose images are all saved,
    ``chunk_key`` what a chunk's images (:func:`chunk_key`), or a merged basis's whole run,
    depend on. A mark that does not read as one is no mark: the chunk is rendered again.
    """

    model_config = ConfigDict(strict=True, frozen=True)

    chunk_complete: Optional[bool] = Field(
        None, description="true: a chunk folder whose images are all saved"
    )
    chunk_run: Optional[ChunkRun] = Field(None, description="where and how fast a chunk rendered")
    chunk_key: Optional[str] = Field(
        None, description="SHA-256 (hex) of what the images, or the merged run, depend on"
    )

    @classmethod
    def of(cls, manifest) -> "ChunkMark":
        """The mark ``manifest`` (a :class:`~mitsuba_manifold.basis.folder.Manifest`) carries
        (an empty one when it carries none, or one that does not read).
        """
        try:
            return cls.model_validate(
                {k: manifest.extra[k] for k in cls.model_fields if k in manifest.extra}
            )
        except ValidationError:
            return cls()

    def put(self, manifest) -> None:
        """Set this mark on ``manifest`` (the keys of an empty mark are removed)."""
        for key in type(self).model_fields:
            manifest.extra.pop(key, None)
        manifest.extra.update(self.model_dump(mode="json", exclude_none=True))


@dataclass(frozen=True)
class ChunkSpec:
    """One chunk to render: plain data, sent to a worker as it is.

    Attributes
    ----------
    scene, manifold : str
        Absolute paths of the scene XML and the saved manifold.
    index, count : int
        Chunk ``index`` of ``count``.
    spp, seed : int
        The chunk's samples per pixel and seed (:func:`chunk_seed`); they replace those of
        :attr:`options` when it is rendered.
    options : BasisOptions
        How the whole basis is rendered (:class:`mitsuba_manifold.render.jobs.render_basis.BasisOptions`).
    """

    scene: str
    manifold: str
    index: int
    count: int
    spp: int
    seed: int
    options: BasisOptions = None

    @property
    def name(self):
        return f"{self.index:03d}-of-{self.count:03d}"


@dataclass
class ChunkResult:
    """What a worker sends back: the chunk's images and manifest, and where and how fast."""

    spec: ChunkSpec
    manifest: basis_folder.Manifest
    images: dict
    seconds: float
    host: str
    pid: int


def chunk_seed(seed, index, count):
    """Seed of chunk ``index`` of ``count`` (see the module docstring)."""
    return int(seed) * int(count) + int(index)


def plan(scene, manifold, chunks, options=None):
    """Split a basis rendered with ``options`` into ``chunks`` :class:`ChunkSpec`.

    Parameters
    ----------
    scene, manifold : str
    chunks : int
    options : BasisOptions, optional
        How the whole basis is rendered (default: :class:`BasisOptions`'s defaults); its
        ``spp`` samples per pixel are split over the chunks, the first ``spp % chunks`` getting
        one more than the others, and its ``seed`` gives the chunks' (:func:`chunk_seed`).
    """
    options = BasisOptions() if options is None else options
    spp, seed, chunks = int(options.sampling.spp), options.sampling.seed, int(chunks)
    if chunks < 1:
        raise MismatchError(f"`chunks` must be >= 1, got {chunks}")
    if spp < chunks:
        raise MismatchError(
            f"`spp` ({spp}) must be at least the number of chunks ({chunks}): "
            "every chunk renders at least one sample per pixel"
        )
    scene, manifold = os.path.abspath(os.fspath(scene)), os.path.abspath(os.fspath(manifold))
    return [
        ChunkSpec(
            scene,
            manifold,
            j,
            chunks,
            spp // chunks + (j < spp % chunks),
            chunk_seed(seed, j, chunks),
            options,
        )
        for j in range(chunks)
    ]


def render_chunk(spec):
    """Render one chunk into a private temporary folder; return its images (a worker's task)."""
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="mitsuba-manifold-chunk-") as tmp:
        manifest = render_basis(
            spec.scene, spec.manifold, tmp, spec.options, spp=spec.spp, seed=spec.seed
        )
        images = {
            key: imageio.read_exr(os.path.join(tmp, entry.file))
            for key, entry in manifest.entries()
        }
        if manifest.cross:
            with np.load(os.path.join(tmp, manifest.cross.file)) as data:
                images[_CROSS] = (data["pairs"], data["images"])
    return ChunkResult(
        spec, manifest, images, time.perf_counter() - t0, socket.gethostname(), os.getpid()
    )


def chunk_folder(out, spec):
    return os.path.join(os.fspath(out), CHUNK_DIR, spec.name)


#: :class:`BasisOptions` fields that do not change a chunk's images (left out of
#: :func:`chunk_settings`); ``spp`` and ``seed`` are the chunk's own (:class:`ChunkSpec`).
NOT_SETTINGS = ("force", "progress", "database", "aovs", "spp", "seed")
#: Fields :func:`chunk_settings` always holds; the others only where they differ from their
#: defaults.
ALWAYS_HASHED = (
    "sensor",
    "materials",
    "near",
    "radius",
    "mode",
    "components",
    "resolution",
    "max_depth",
    "variant",
    "x",
)

#: How :func:`chunk_settings` spells ``components="full"``: its former name, so that the chunks
#: of a basis rendered before keep their keys.
KEYED_FULL = "auto"


def chunk_settings(options):
    """The :class:`BasisOptions` fields that a chunk's images depend on, as ``{name: value}``
    (the part of :func:`chunk_key` that the options give).

    Every field but those of :data:`NOT_SETTINGS`: the fields of :data:`ALWAYS_HASHED`, and
    each other one where it differs from its default (a field added to :class:`BasisOptions`
    with a default leaves the keys of chunks rendered before unchanged).
    """
    default = BasisOptions().keywords()
    hashed = {
        name: value
        for name, value in options.keywords().items()
        if name not in NOT_SETTINGS and (name in ALWAYS_HASHED or value != default[name])
    }
    if hashed.get("components") == "full":  # hashed as spelled when chunks were first keyed
        hashed["components"] = KEYED_FULL
    return hashed


def identities(spec):
    """``(scene hash, manifold identity)`` of a chunk's scene and manifold files."""
    return basis_folder.scene_hash(spec.scene), basis_folder.manifold_file_identity(spec.manifold)


def chunk_key(spec, ids=None):
    """SHA-256 (hex) of what chunk ``spec``'s images depend on: index, count, spp, seed, the render
    options and the identities of its scene and manifold (``ids``: :func:`identities`).
    """
    options = chunk_settings(spec.options)
    head = json.dumps(
        {
            "index": spec.index,
            "count": spec.count,
            "spp": spec.spp,
            "seed": spec.seed,
            "options": options,
        },
        sort_keys=True,
        default=repr,
    )
    return key_hash("chunk-v1", head, *(ids or identities(spec)))


def chunk_done(folder, key=None):
    """The manifest of a completely saved chunk folder (of ``chunk_key`` ``key``, when given, with
    every image as saved), else None.
    """
    try:
        manifest = basis_folder.Manifest.read(folder)
    except MismatchError:
        return None
    mark = ChunkMark.of(manifest)
    if not mark.chunk_complete or (key is not None and mark.chunk_key != key):
        return None
    for _, entry in manifest.entries():
        if not os.path.isfile(os.path.join(folder, entry.file)) or basis_folder.image_changed(
            folder, entry
        ):
            return None
    return manifest


#: Key of a chunk's cross terms among its images (``(pairs, float16 images)``).
_CROSS = "cross:"


def save_chunk(out, result, key=None):
    """Write a worker's chunk into its folder: images (their hashes recorded), then the manifest
    (the completion mark; ``key``: the chunk's :func:`chunk_key`, recorded).
    """
    folder = chunk_folder(out, result.spec)
    os.makedirs(folder, exist_ok=True)
    manifest = result.manifest.copy()  # the entries get this folder's hashes
    for key_, entry in result.manifest.entries():
        imageio.write_exr(os.path.join(folder, entry.file), result.images[key_])
        manifest.set_entry(key_, replace(entry, sha256=file_hash(os.path.join(folder, entry.file))))
    if result.manifest.cross:
        digest = write_cross(
            os.path.join(folder, result.manifest.cross.file), *result.images[_CROSS]
        )
        manifest.cross = replace(manifest.cross, sha256=digest)
    run = ChunkRun(seconds=float(result.seconds), host=str(result.host), pid=int(result.pid))
    ChunkMark(chunk_complete=True, chunk_run=run, chunk_key=key).put(manifest)
    manifest.write(folder)
    return manifest


def merge(out, folders, seed, force=False):
    """Merge complete chunk folders into the basis folder ``out``: the spp-weighted mean.

    Returns the merged manifest. Images ``out`` already holds for the same settings are
    kept (a merge killed half-way resumes); a basis of other settings, or files the basis
    did not make (unless ``force``), are refused. ``out`` is locked while merging.
    """
    with FolderLock(os.fspath(out), "basis folder"):
        return _merge(out, folders, seed, force)


def _merge(out, folders, seed, force, run_key=None):
    manifests = [basis_folder.Manifest.read(f) for f in folders]
    first = manifests[0]
    for f, m in zip(folders[1:], manifests[1:]):
        diff = first.differences(m, ignore=("spp", "seed", "chunks"))
        if (
            diff
            or set(m.images) != set(first.images)
            or m.components != first.components
            or set(dict(m.entries())) != set(dict(first.entries()))
        ):
            raise MismatchError(
                f"chunk {f} does not match chunk {folders[0]} "
                f"({', '.join(diff) or 'images'} differ); delete {os.path.dirname(f)}"
            )
    spp = np.array([m.spp for m in manifests], dtype=np.float64)
    merged = replace(
        first.copy(),
        settings=replace(first.settings, spp=int(spp.sum()), seed=int(seed)),
        chunks=len(folders),
        images={},
        gi_images=None,
    )
    ChunkMark().put(merged)  # a merged basis is no chunk
    files = [e.file for _, e in first.entries()] + [basis_folder.MANIFEST]
    merged.images = open_folder(out, merged, files, force)
    done = {e.file for e in merged.images.values()}
    # listed as pending before the first is written: an interrupted merge leaves files the same
    # command knows as its own (removed and merged again); the manifest is rewritten as images land
    merged.pending = sorted(f for f in files[:-1] if f not in done)
    merged.write(out)
    weights = spp / spp.sum()
    last_write = time.perf_counter()
    for key, entry in first.entries():
        gi = key.startswith(basis_folder.GI)
        section, plain = ("gi_images", key[len(basis_folder.GI) :]) if gi else ("images", key)
        if plain in (getattr(merged, section) or {}):
            continue
        if time.perf_counter() - last_write > 1.0:  # progress kept for a resumed merge
            merged.write(out)
            last_write = time.perf_counter()
        acc = None
        for f, m, w in zip(folders, manifests, weights):
            file = getattr(m, section)[plain].file
            img = imageio.read_exr(os.path.join(f, file)).astype(np.float64) * w
            acc = img if acc is None else acc + img
        imageio.write_exr(os.path.join(out, entry.file), acc.astype(np.float32))
        merged.section(section)[plain] = basis_folder.ImageEntry(
            file=entry.file,
            time_s=float(sum(getattr(m, section)[plain].time_s for m in manifests)),
            sha256=file_hash(os.path.join(out, entry.file)),
        )
    if first.cross:  # the cross terms: the same spp-weighted mean
        acc, pairs = None, None
        for f, m, w in zip(folders, manifests, weights):
            with np.load(os.path.join(f, m.cross.file)) as data:
                if pairs is not None and list(data["pairs"].ravel()) != list(pairs.ravel()):
                    raise MismatchError(
                        f"chunk {f} holds cross terms of other pairs; delete {os.path.dirname(f)}"
                    )
                pairs, img = data["pairs"], data["images"].astype(np.float64) * w
            acc = img if acc is None else acc + img
        digest = write_cross(os.path.join(out, first.cross.file), pairs, acc)
        merged.cross = replace(first.cross, sha256=digest)
    if run_key is not None:  # the mark of a finished run (written with its last image)
        ChunkMark(chunk_key=run_key).put(merged)
    merged.pending = None
    merged.write(out)
    return merged


@dataclass
class ChunkedRun:
    """What :func:`render_chunked` did: the merged manifest and per-chunk timings."""

    manifest: basis_folder.Manifest
    rendered: list  # (chunk name, seconds, host, pid) of the chunks rendered in this call
    resumed: list  # names of chunks found complete
    wall_s: float
    merge_s: float


def render_chunked(
    scene, manifold, out, options=None, *, chunks=1, executor=None, keep_chunks=False, **settings
):
    """Render a basis as ``chunks`` chunks with ``executor`` and merge them into ``out``.

    Parameters
    ----------
    scene, manifold, out : str
    options : BasisOptions, optional
        How to render the basis, as :func:`~mitsuba_manifold.render.jobs.render_basis.render_basis`
        (default: :class:`BasisOptions`'s defaults). Its ``spp`` and ``seed`` are those of the
        merged basis, split over the chunks (chunk seeds: :func:`chunk_seed`); ``progress``
        prints a line per chunk, and ``aovs`` writes the denoising guides of the merged basis
        (rendered here, once).
    chunks : int
    executor : LocalExecutor or RayExecutor, optional
        Default: :class:`mitsuba_manifold.render.jobs.executor.LocalExecutor`.
    keep_chunks : bool
        Keep ``<out>/.chunks`` after merging.
    **settings
        Fields of the groups of :class:`BasisOptions` by name (``spp=64, mode="onepass"``),
        which override those of ``options`` (:meth:`BasisOptions.updated`).

    Returns
    -------
    ChunkedRun

    Raises
    ------
    TypeError
        A keyword that is not a field of ``BasisOptions``, before anything is written.
    """
    options = (BasisOptions() if options is None else options).updated(**settings)
    run_opts = options.run
    # the chunks: no progress bar of their own, the guides rendered once for the merged basis
    specs = plan(scene, manifold, chunks, options.updated(progress=False, aovs=False))
    spp, seed, force = options.sampling.spp, options.sampling.seed, run_opts.force
    check_foreign_folder(os.fspath(out), force)  # before any chunk is rendered
    _check_out(out, specs[0], spp, seed, chunks)
    ids = identities(specs[0])
    keys = [chunk_key(s, ids) for s in specs]
    run_key = key_hash("chunked-run-v1", *keys)
    t0 = time.perf_counter()
    with FolderLock(os.fspath(out), "basis folder"):
        manifest = _finished(out, run_key)
        if manifest is not None:  # the same command on a finished basis: nothing to render
            run = ChunkedRun(manifest, [], [s.name for s in specs], 0.0, 0.0)
        else:
            run = _render_and_merge(
                out, specs, keys, run_key, executor, run_opts.progress, seed, force
            )
        if run_opts.aovs:
            ensure_aovs(out, run.manifest)
        if not keep_chunks:
            shutil.rmtree(os.path.join(out, CHUNK_DIR), ignore_errors=True)
    run.wall_s = time.perf_counter() - t0
    return run


def render_view(scene, manifold, out, options, chunks=1, executor=None, keep_chunks=False):
    """The basis of one view: rendered here (:func:`~mitsuba_manifold.render.jobs.render_basis.render_basis`)
    where it is one chunk on the local executor, else in ``chunks`` chunks by ``executor``
    (:func:`render_chunked`); returns its manifest.
    """
    if chunks == 1 and getattr(executor, "name", "local") == "local":
        return render_basis(scene, manifold, out, options)
    return render_chunked(
        scene,
        manifold,
        out,
        options,
        chunks=chunks,
        executor=executor,
        keep_chunks=keep_chunks,
    ).manifest


def _finished(out, run_key):
    """The manifest of ``out`` when it holds the merged basis of the run ``run_key`` with every
    image as merged, else None.
    """
    try:
        manifest = basis_folder.Manifest.read(out)
    except MismatchError:
        return None
    if ChunkMark.of(manifest).chunk_key != run_key:
        return None
    entries = manifest.entries()
    if any(
        not os.path.isfile(os.path.join(out, e.file)) or basis_folder.image_changed(out, e)
        for _, e in entries
    ):
        return None
    return manifest


def _render_and_merge(out, specs, keys, run_key, executor, progress, seed, force):
    from .executor import LocalExecutor

    executor = executor or LocalExecutor()
    key_of = dict(zip((s.name for s in specs), keys))
    resumed = [s.name for s in specs if chunk_done(chunk_folder(out, s), key_of[s.name])]
    todo = [s for s in specs if s.name not in resumed]
    rendered = []

    def run(batch):
        for result in executor.map(render_chunk, batch):
            save_chunk(out, result, key_of[result.spec.name])
            rendered.append((result.spec.name, result.seconds, result.host, result.pid))
            if progress:
                print(
                    f"  chunk {result.spec.name}: {result.spec.spp} spp in {result.seconds:.1f} s "
                    f"({result.host}, pid {result.pid})",
                    flush=True,
                )

    if len(specs) > 1 and _chooses_pairs(specs[0].options):  # the first chunk's pairs for all
        run([s for s in todo if s.index == 0])
        follow = _first_choice(chunk_folder(out, specs[0]))
        todo = [replace(s, options=s.options.updated(**follow)) for s in todo if s.index != 0]
    run(todo)
    t1 = time.perf_counter()
    manifest = _merge(out, [chunk_folder(out, s) for s in specs], seed, force, run_key)
    return ChunkedRun(manifest, rendered, resumed, 0.0, time.perf_counter() - t1)


def _chooses_pairs(options):
    """Whether a chunk of ``options`` chooses cross-term pairs on its first pass."""
    return (
        options.sampling.mode == "onepass"
        and options.gi.components == "full"
        and options.gi.cross_light_tol
        and options.gi.cross_keep is None
    )


def _first_choice(folder):
    """Options that make a later chunk keep what the first chunk (in ``folder``) chose."""
    manifest = basis_folder.Manifest.read(folder)
    if "l2+" not in manifest.held_components:
        return {}
    if manifest.cross is None:
        return {"cross_keep": []}
    with np.load(os.path.join(folder, manifest.cross.file)) as data:
        return {"cross_keep": [tuple(str(v) for v in p) for p in data["pairs"]]}


def _check_out(out, spec, spp, seed, chunks):
    """Refuse early (before rendering) an ``out`` holding a basis of other settings (one that lists
    no image yet, e.g. of a run that failed before its first, has nothing to lose: as :func:`open_folder`).
    """
    if not os.path.exists(os.path.join(os.fspath(out), basis_folder.MANIFEST)):
        return
    old = basis_folder.Manifest.read(out)
    if not old.images:
        return
    want = {
        "spp": int(spp),
        "seed": int(seed),
        "chunks": int(chunks),
        "scene_hash": basis_folder.scene_hash(spec.scene),
        "manifold_hash": (
            basis_folder.manifold_file_identity(spec.manifold)
            if old.version >= 2
            else file_hash(spec.manifold)
        ),
        "mode": spec.options.sampling.mode,
    }
    diff = [k for k, v in want.items() if getattr(old, k) != v]
    if diff:
        raise MismatchError(
            f"{out} holds a basis made with other settings ({', '.join(diff)} differ); "
            "choose another folder or delete it"
        )
