"""One-pass basis rendering: the base image and every material's touch image from one set of paths.

For paths scattering once off the target, the material enters only at that vertex
(paper Sec. 5.2, issue 5): the paths are traced once with a sampling density that
covers every material, that vertex is recorded, and each material's image is a sparse
product ``(pixels x bins) @ (bins x materials)`` of the recorded *splats* with the
tables. :class:`TableSplats` computes it directly (nearest lookups, box filter),
:class:`FilterSplats` through image blocks with the film's filter.
"""

import os
import threading
from dataclasses import dataclass
from typing import NamedTuple

import drjit as dr
import mitsuba as mi
import numpy as np

from ..._util.cache import key_hash, npy_cache
from ...errors import InputError
from ..lookups import merl_angles, merl_bin
from .common import primary_rays, seeded_sampler, target_groups


#: Materials per packet of the table product (Dr.Jit packet gathers of 16 contiguous floats).
PACKET = 16
#: Most bytes of per-pixel sums one table kernel holds (Expand mode keeps a copy per thread).
_SUM_BYTES = 1 << 28
_NO_BIN = 0xFFFFFFFF


def _prefetch(path, block=1 << 24):
    """Read ``path`` in a background thread, so that it is in the page cache when needed."""
    def run():
        try:
            buf = bytearray(block)
            with open(path, "rb", buffering=0) as f:
                while f.readinto(buf):
                    pass
        except OSError:
            pass
    threading.Thread(target=run, daemon=True).start()


def _mixture_table(db, rows, mix, keep=2):
    """``sum_k mix_k table_k`` from the interleaved tables ``rows``, as ``(bins, 3)`` float32.

    Cached beside ``rows`` (keyed by them and the weights; the ``keep`` newest kept), so
    that a later render need not read every table before it starts tracing.
    """
    key = os.path.basename(rows.filename).split(".")[0]
    digest = key_hash(np.asarray(mix, dtype=np.float64), length=16)
    path = os.path.join(db.cache_dir, f"{key}.mixture-v1-{digest}.npy")
    shape = (rows.shape[0], 3)

    def build():
        w = np.zeros(rows.shape[2], dtype=np.float32)
        w[:len(mix)] = mix
        return (np.asarray(rows).reshape(-1, rows.shape[2]) @ w).reshape(shape)

    return npy_cache(path, build, shape=shape, dtype=np.float32, finite=True, touch=True,
                     keep=keep, marker=".mixture-v1-")


def _splat_rows(sums, splats, pixel, rows, row_packets, kb0, kb1):
    """Add ``a * max(rows[bin], 0)`` of every splat to its pixel's sums, for material packets
    ``kb0 .. kb1 - 1``.

    ``splats`` holds ``(bin bits, a.r, a.g, a.b)`` per splat and ``pixel`` its row of
    ``sums`` (laid out ``(pixels, 3, (kb1 - kb0) * PACKET)``); ``rows`` is the flat
    ``(bins, 3, row_packets * PACKET)`` table. One lane per splat and packet: a packet
    gather from the table, a packet scatter-add into a per-thread copy of ``sums``.
    """
    nb = kb1 - kb0
    lane = dr.arange(mi.UInt32, dr.width(pixel) * nb)
    s = lane // nb
    kb = lane - s * nb
    data = dr.gather(mi.Vector4f, splats, s)
    b = dr.reinterpret_array(mi.UInt32, data.x)
    q = dr.gather(mi.UInt32, pixel, s)
    threshold = dr.expand_threshold()
    dr.set_expand_threshold(max(threshold, dr.width(sums)))
    try:
        for c in range(3):
            t = dr.gather(mi.ArrayXf, rows, (b * 3 + c) * row_packets + kb0 + kb,
                          shape=(PACKET, dr.width(lane)))
            dr.scatter_add(sums, dr.maximum(t, 0.0) * data[c + 1], (q * 3 + c) * nb + kb,
                           mode=dr.ReduceMode.Expand)
        dr.eval(sums)
    finally:
        dr.set_expand_threshold(threshold)


class TableSplats:
    """The splats of :func:`render_onepass` as per-pixel sums ``sum a * table(bin)`` of every
    material: nearest lookups, box filter (each sample lands in one pixel).

    Sums are kept per chunk of materials, laid out ``(pixels, 3, materials padded to
    PACKET)``. When a chunk's sums of the whole image, copied once per thread, exceed
    ``_SUM_BYTES``, the splats are processed in tiles of pixels into smaller sums first.
    """

    def __init__(self, block, rows, names, chunks, dims):
        self.block, self.names, self.dims = block, names, dims
        self.n_pad = int(rows.shape[2])
        self.rows = mi.Float(np.asarray(rows).reshape(-1))  # maps the cached file, no copy
        self.pixels = int(dr.prod(block.size()))
        self.packets = [(k0 // PACKET, -(-k1 // PACKET)) for k0, k1 in chunks]
        self.chunks = chunks
        self.sums = [dr.zeros(mi.Float, self.pixels * 3 * (b1 - b0) * PACKET) for b0, b1 in self.packets]
        widest = max(b1 - b0 for b0, b1 in self.packets) * PACKET
        self.tile = max(1, _SUM_BYTES // (12 * widest * max(1, dr.thread_count())))
        self.tiles = []

    def prepare(self, rec, beta, pos):
        """Turn one pass's records into splats, sorted by bin within tiles of pixels."""
        size, offset = self.block.size(), self.block.offset()
        x = mi.Int32(dr.floor(pos.x)) - offset.x
        y = mi.Int32(dr.floor(pos.y)) - offset.y
        pixel = mi.UInt32(y * size.x + x)
        keys, amps = [], []
        for wo, a in ((rec["wo_nee"], rec["e_nee"]), (rec["wo"], rec["g"])):
            a = beta * a * wo.z
            ok = (rec["wi"].z > 0) & (wo.z > 0) & dr.any(a != 0)
            keys.append(dr.select(ok, merl_bin(*merl_angles(rec["wi"], wo), self.dims), _NO_BIN))
            amps.append(a)
        dr.eval(self.block.tensor(), pixel, keys, amps)
        # Both splats of every sample in sample order (so in pixel order), compacted.
        j = dr.arange(mi.UInt32, 2 * dr.width(pixel))
        key = dr.select((j & 1) != 0, dr.gather(mi.UInt32, keys[1], j >> 1),
                        dr.gather(mi.UInt32, keys[0], j >> 1))
        idx = dr.compress(key != _NO_BIN)
        self.tiles = []
        if dr.width(idx) == 0:
            return
        second = (idx & 1) != 0
        amp = dr.select(second, dr.gather(mi.Color3f, amps[1], idx >> 1),
                        dr.gather(mi.Color3f, amps[0], idx >> 1))
        key = dr.gather(mi.UInt32, key, idx)
        pix = dr.gather(mi.UInt32, pixel, idx >> 1)
        dr.eval(key, amp, pix)
        # Sorted by bin within each tile (a stable 16-bit radix sort of the bins' leading
        # bits is enough to read the tables in order).
        shift = max(0, (int(np.prod(self.dims)) - 1).bit_length() - 16)
        short = (key.numpy() >> shift).astype(np.uint16)
        pix_np = pix.numpy()
        starts = np.arange(0, self.pixels, self.tile)
        bounds = np.searchsorted(pix_np, np.append(starts, self.pixels))
        for p0, lo, hi in zip(starts, bounds[:-1], bounds[1:]):
            if hi == lo:
                continue
            order = mi.UInt32(lo + np.argsort(short[lo:hi], kind="stable").astype(np.uint32))
            a = dr.gather(mi.Color3f, amp, order)
            splats = mi.Vector4f(dr.reinterpret_array(mi.Float, dr.gather(mi.UInt32, key, order)),
                                 a.x, a.y, a.z)
            splats = dr.ravel(splats)  # (bin, r, g, b) per splat, contiguous
            local = dr.gather(mi.UInt32, pix, order) - int(p0)
            dr.eval(splats, local)
            self.tiles.append((int(p0), min(self.pixels, int(p0) + self.tile), splats, local))

    def add(self, c):
        """Add the splats of the prepared pass to the sums of chunk ``c``'s materials."""
        kb0, kb1 = self.packets[c]
        width = 3 * (kb1 - kb0) * PACKET
        for p0, p1, splats, local in self.tiles:
            if p1 - p0 == self.pixels:
                _splat_rows(self.sums[c], splats, local, self.rows, self.n_pad // PACKET, kb0, kb1)
            else:
                part = dr.zeros(mi.Float, (p1 - p0) * width)
                _splat_rows(part, splats, local, self.rows, self.n_pad // PACKET, kb0, kb1)
                i = dr.arange(mi.UInt32, dr.width(part))
                dr.scatter_add(self.sums[c], part, i + p0 * width, mode=dr.ReduceMode.NoConflicts)
                dr.eval(self.sums[c])

    def release(self):
        self.tiles = []

    def images(self, film):
        """Each material's sums divided by the filter weights of all samples."""
        block = np.array(self.block.tensor())
        weight = block[..., -1].reshape(-1)
        scale = mi.Float(np.where(weight > 0, 1.0 / np.where(weight > 0, weight, 1.0), 0.0))
        shape = block.shape[:2] + (3,)
        images = {}
        for (k0, k1), (kb0, kb1), sums in zip(self.chunks, self.packets, self.sums):
            # (pixels, 3, packets) -> (materials, pixels, 3), scaled
            width = (kb1 - kb0) * PACKET
            lane = dr.arange(mi.UInt32, (k1 - k0) * self.pixels * 3)
            k = lane // (self.pixels * 3)
            r = lane - k * (self.pixels * 3)
            p = r // 3
            out = dr.gather(mi.Float, sums, r * width + k + (k0 - kb0 * PACKET)) * dr.gather(mi.Float, scale, p)
            out = out.numpy().reshape((k1 - k0,) + shape)
            for k, name in enumerate(self.names[k0:k1]):
                images[name] = out[k]
        return images


class FilterSplats:
    """The splats of :func:`render_onepass` put into image blocks with the film's filter,
    each material evaluated at them (``nearest``: one gather from its table; ``linear``: the
    BSDF's own ``eval``)."""

    def __init__(self, film, block, names, chunks, db, path, options, several_passes):
        self.film, self.block, self.names, self.chunks = film, block, names, chunks
        self.db, self.path, self.options = db, path, options
        self.dims = tuple(int(d) for d in db.dims)
        bins = int(np.prod(self.dims))
        self.nearest = options["interpolation"] == "nearest"
        self.blocks = [mi.ImageBlock(block.size(), block.offset(), 3 * (k1 - k0), film.rfilter(),
                                     border=block.has_border(), normalize=block.normalize(),
                                     coalesce=block.coalesce()) for k0, k1 in chunks]
        self.cache = {}  # chunk index -> tables (nearest) or BSDFs (linear)
        self.keep = several_passes and len(names) * bins * 12 <= (1 << 31)
        if self.nearest:  # planar (RGB, bins) -> interleaved (bins, RGB)
            i = dr.arange(mi.UInt32, 3 * bins)
            self.interleave = (i % 3) * bins + i // 3
        self.splats = []

    def _data(self, c):
        if c in self.cache:
            return self.cache[c]
        k0, k1 = self.chunks[c]
        if self.nearest:  # each table as (bins, RGB), clamped at 0 as the BSDF does
            data = [dr.maximum(dr.gather(mi.Float, mi.Float(np.ascontiguousarray(
                self.db.reflectance(n), np.float32).reshape(-1)), self.interleave), 0.0)
                for n in self.names[k0:k1]]
            dr.eval(data)
        else:
            data = [mi.load_dict({"type": "manifold_brdf", "manifold": self.path, "material": n,
                                  "sampling": "cosine", **self.options}) for n in self.names[k0:k1]]
        if self.keep:
            self.cache[c] = data
        return data

    def prepare(self, rec, beta, pos):
        """Two splat sets (light connection, sampled direction), compacted, sorted by bin."""
        dr.eval(self.block.tensor(), beta, rec, pos)
        self.splats = []
        for wo, a in ((rec["wo_nee"], rec["e_nee"]), (rec["wo"], rec["g"])):
            a = beta * a * wo.z
            ok = (rec["wi"].z > 0) & (wo.z > 0) & dr.any(a != 0)
            key = merl_bin(*merl_angles(rec["wi"], wo), self.dims)
            key = np.array(dr.select(ok, key, _NO_BIN), dtype=np.uint32)
            order = np.argsort(key, kind="stable")[:int(np.count_nonzero(key != _NO_BIN))]
            if order.size == 0:
                continue
            idx = mi.UInt32(order.astype(np.uint32))
            pick = lambda v: dr.gather(type(v), v, idx)  # noqa: E731
            splat = dict(pos=pick(pos), a=pick(a), bin=mi.UInt32(key[order]))
            if not self.nearest:  # the BSDF's own lookup; eval returns f cos: undo cos
                splat["si"] = dr.zeros(mi.SurfaceInteraction3f, order.size)
                splat["si"].wi = pick(rec["wi"])
                splat["wo"] = pick(wo)
                splat["a"] = splat["a"] / splat["wo"].z
            dr.eval(splat)
            self.splats.append(splat)

    def add(self, c):
        if not self.splats:
            return
        data, block, ctx = self._data(c), self.blocks[c], mi.BSDFContext()
        for splat in self.splats:
            values = []
            for table in data:
                if self.nearest:
                    v = dr.gather(mi.Color3f, table, splat["bin"]) * splat["a"]
                else:
                    v = table.eval(ctx, splat["si"], splat["wo"]) * splat["a"]
                values += [v.x, v.y, v.z]
            block.put(splat["pos"], values)
            dr.eval(block.tensor())

    def release(self):
        self.splats = []

    def images(self, film):
        """Develop as the film does: the material channels as AOVs of the base block,
        normalised by the filter weights of all samples."""
        head = np.array(self.block.tensor())
        images = {}
        for (k0, k1), block in zip(self.chunks, self.blocks):
            aovs = [f"m{k}.{c}" for k in range(k1 - k0) for c in "RGB"]
            film.prepare(aovs)
            merged = np.concatenate([head, np.array(block.tensor())], axis=-1)
            film.put_block(mi.ImageBlock(mi.TensorXf(merged), self.block.offset(), film.rfilter(),
                                         border=self.block.has_border(),
                                         normalize=self.block.normalize(),
                                         coalesce=self.block.coalesce()))
            img = np.array(film.develop(), dtype=np.float32)
            start = img.shape[-1] - len(aovs)
            for k, name in enumerate(self.names[k0:k1]):
                images[name] = img[..., start + 3 * k:start + 3 * k + 3].copy()
        return images



def render_onepass(integrator, scene, materials=None, spp=0, seed=0, sensor=0, chunk=None,
                   max_samples=1 << 22, spp_per_pass=None, progress=None):
    """Render the base image and every material's touch image from one set of paths.

    For paths scattering once off the target, the material enters only at that
    vertex (issue 5). The paths are traced once; on the target they sample a density
    ``q`` that covers every material (the ``manifold_brdf`` sampling density of the
    mixture ``sum_i P_i / |P_i|`` of the per-material densities, plus its cosine
    fraction), and that vertex is recorded (:meth:`ManifoldPathIntegrator.trace_paths`). Its two directions (the
    light connection, the sampled one) become two *splats* per sample, kept where
    they carry light: a pixel, a MERL bin, an RGB amplitude ``a``. A material adds
    ``a * table(bin)`` to the pixel, so the images are a sparse product
    ``(pixels x bins) @ (bins x materials)``.

    With ``nearest`` lookups and a box filter (the usual case), that product is
    computed directly: the tables, interleaved by bin (``Database.material_rows``,
    cached beside the database), give all materials' values at a bin in one
    contiguous read; the splats are sorted by bin, so the tables are read in order;
    one Dr.Jit kernel per group of ``chunk`` materials adds ``a * row`` into
    per-pixel sums (scatter-adds into per-thread copies, ``ReduceMode.Expand``),
    over tiles of pixels small enough to bound that memory. Otherwise (``linear``
    lookups, other filters) each material is evaluated at the splats sorted by bin
    (one gather from its table, or the BSDF's own ``eval``) and splatted with the
    film's filter. Either way the images are normalised by the filter weights of all
    samples, as the film does. Samples are processed in passes of at most
    ``max_samples`` paths to bound memory. Each image is an unbiased estimate of
    what ``component="touch"`` renders with that material alone; the images are
    correlated (the same paths).

    Parameters
    ----------
    integrator : ManifoldPathIntegrator
        The ``manifold_path`` instance (its ``target``, ``max_depth`` and path tracer).
    scene : mi.Scene
        Its target (``target`` parameter) must be one group of ``manifold_brdf``
        BSDFs on one manifold. The scene's materials are not modified.
    materials : list of str, optional
        Training materials of the manifold to render (default: all).
    spp, seed, sensor :
        As :meth:`render` (``spp=0``: the sensor's sample count).
    chunk : int, optional
        Materials per kernel (default: all of them with the table product, 16
        otherwise).
    max_samples : int
        Most paths traced at once (passes of whole samples per pixel).
    spp_per_pass : int, optional
        Samples per pixel per pass, instead of the most that ``max_samples`` allows.
    progress : callable, optional
        Called as ``progress(done, total)`` in work units (one per pass and chunk).

    Returns
    -------
    OnePassImages
        ``base`` (ndarray float32 (H, W, 3): the paths that never scatter off the target)
        and ``images`` (dict of str -> ndarray float32 (H, W, 3): the touch image of each
        material, in the order of ``materials``).
    """

    target = one_target(scene, integrator.target)
    names = _material_names(target.manifold, target.path, materials)
    if spp_per_pass is not None and int(spp_per_pass) < 1:
        raise InputError(f"manifold_path: spp_per_pass must be >= 1, got {spp_per_pass}")
    if chunk is not None and int(chunk) < 1:
        raise InputError(f"manifold_path: chunk must be >= 1, got {chunk}")

    if isinstance(sensor, int):
        sensor = scene.sensors()[sensor]
    film = sensor.film()
    db = target.manifold.open_database(target.database, names)
    dims = tuple(int(d) for d in db.dims)
    # The table product needs nearest lookups, a box filter (one pixel per sample)
    # and tables addressable with 32-bit indices.
    n_pad = -(-len(names) // PACKET) * PACKET
    rows = None
    if (target.interpolation == "nearest" and film.rfilter().is_box_filter()
            and int(np.prod(dims)) * 3 * n_pad < 1 << 32):
        rows = db.material_rows(names, pad=PACKET)
        _prefetch(rows.filename)  # read while the paths are traced
    proxy = _sampling_proxy(target, db, names, rows)

    spp = int(spp) or sensor.sampler().sample_count()
    passes = _passes(film, spp, max_samples, spp_per_pass)
    chunk = int(chunk) if chunk else (len(names) if rows is not None else 16)
    chunks = [(i, min(len(names), i + chunk)) for i in range(0, len(names), chunk)]
    alpha = mi.has_flag(film.flags(), mi.FilmFlags.Alpha)
    plan = dict(groups=target.groups, select=1, keep=3, aovs=[])

    film.prepare([])
    base_block = film.create_block()
    base_block.set_coalesce(base_block.coalesce() and spp >= 4)
    if rows is None:
        splat = FilterSplats(film, base_block, names, chunks, db, target.path, target.options(),
                             len(passes) > 1)
    else:
        splat = TableSplats(base_block, rows, names, chunks, dims)

    done, total = 0, len(passes) * len(chunks)
    with dr.suspend_grad():
        for p, n_spp in enumerate(passes):
            sampler = seeded_sampler(sensor, seed * len(passes) + p, n_spp)
            ray, weight, pos = primary_rays(scene, sensor, sampler)
            L, valid, _, rec = integrator.trace_paths(scene, sampler, ray, mi.Bool(True), plan, True, proxy)
            L = L * weight
            head = [L.x, L.y, L.z] + ([dr.select(valid, 1.0, 0.0)] if alpha else [])
            base_block.put(pos, head + [mi.Float(1.0)])
            splat.prepare(rec, rec["beta"] * weight, pos)
            del sampler, ray, L, valid, rec, head
            for c in range(len(chunks)):
                splat.add(c)
                done += 1
                if progress is not None:
                    progress(done, total)
            splat.release()
    film.prepare([])
    film.put_block(base_block)
    base = np.array(film.develop(), dtype=np.float32)[..., :3].copy()
    return OnePassImages(base, splat.images(film))


class OnePassImages(NamedTuple):
    """:func:`render_onepass`: the base image and each material's touch image."""

    base: np.ndarray
    images: dict


@dataclass(frozen=True)
class OnePassTarget:
    """The one target group of a one-pass render and what its ``manifold_brdf`` BSDFs share."""

    groups: list
    manifold: object
    path: str
    database: object
    interpolation: str
    sampling: str

    def options(self):
        """``manifold_brdf`` parameters that make a BSDF look tables up as the target does."""
        out = {"interpolation": self.interpolation}
        if self.database is not None:
            out["database"] = self.database
        return out


def one_target(scene, target):
    """The single target group of ``scene`` for the integrator's ``target`` parameter, checked."""
    groups = target_groups(scene, target)
    if len(groups) != 1:
        raise InputError(
            f"manifold_path: one-pass rendering handles one target group, the target "
            f"{target!r} gives {len(groups)} ({[g[0] for g in groups]}); render "
            "several targets material by material")
    bsdfs = groups[0][1]   # manifold_brdf instances: target_groups only returns those
    first = bsdfs[0]
    for b in bsdfs[1:]:
        same = (os.path.samefile(b.manifold_path, first.manifold_path)
                and b.interpolation == first.interpolation and b.database == first.database)
        if not same:
            raise InputError(
                f"manifold_path: target BSDFs {first.id()!r} and {b.id()!r} differ in "
                "manifold, database or interpolation; one-pass rendering needs them alike")
    return OnePassTarget(groups, first.manifold, first.manifold_path, first.database,
                         first.interpolation, first.sampling)


def _material_names(manifold, path, materials):
    names = list(manifold.names) if materials is None else [str(n) for n in materials]
    unknown = [n for n in names if n not in manifold.names]
    if unknown or not names or len(set(names)) != len(names):
        raise InputError(
            f"manifold_path: materials must be distinct names of the manifold {path}; "
            f"unknown: {unknown or 'none'} (it has {', '.join(manifold.names[:8])}, ...)")
    return names


def _sampling_proxy(target, db, names, rows):
    """A ``manifold_brdf`` sampling a density that covers every material: the mixture
    ``sum_i P_i / |P_i|`` of the per-material sampling densities (paper Sec. 5.3)."""
    from ..sampling import material_density

    mass = np.array([material_density(db, n).sum() for n in names], float)
    top = mass.max()
    mix = 1.0 / np.maximum(mass, 1e-3 * top) if top > 0 else np.ones(len(names))
    mix /= mix.sum()
    spec = {"type": "manifold_brdf", "manifold": target.path, "prune": 0.0,
            "sampling": target.sampling, **target.options()}
    if rows is None:
        return mi.load_dict({**spec, "weights": ", ".join(f"{n}:{float(w)!r}" for n, w in zip(names, mix))})
    # the mixture's table from the interleaved tables (cached)
    dims = tuple(int(d) for d in db.dims)
    table = _mixture_table(db, rows, mix).T.reshape((3,) + dims)
    proxy = mi.load_dict({**spec, "material": names[0]})
    proxy.set_weights(dict(zip(names, mix)), table=table)
    return proxy


def _passes(film, spp, max_samples, spp_per_pass):
    """Samples per pixel of each pass: at most ``max_samples`` paths (or ``spp_per_pass``) at once."""
    size = film.crop_size()
    if film.sample_border():
        size += 2 * film.rfilter().border_size()
    pixels = int(size[0]) * int(size[1])
    pass_spp = int(spp_per_pass) if spp_per_pass else int(max_samples) // max(pixels, 1)
    pass_spp = max(1, min(spp, pass_spp))
    return [pass_spp] * (spp // pass_spp) + ([spp % pass_spp] if spp % pass_spp else [])
