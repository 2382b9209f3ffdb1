"""The splats of one pass of :func:`~.onepass.render_onepass`, turned into every material's image.

A sample's vertex on the target becomes two *splats* (light connection, sampled direction):
a pixel, a MERL bin, an RGB amplitude ``a``; a material adds ``a * table(bin)`` to the pixel,
so the images are a sparse product ``(pixels x bins) @ (bins x materials)``.
:class:`TableSplats` computes it directly (nearest lookups, box filter), :class:`FilterSplats`
through image blocks with the film's filter.
"""

import drjit as dr
import mitsuba as mi
import numpy as np

from ..lookups import merl_angles, merl_bin


#: Materials per packet of the table product (Dr.Jit packet gathers of 16 contiguous floats).
PACKET = 16
#: Most bytes of per-pixel sums one table kernel holds (Expand mode keeps a copy per thread).
_SUM_BYTES = 1 << 28
_NO_BIN = 0xFFFFFFFF


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

    def pixel_of(self, pos):
        """Row of each sample's pixel in the sums (box filter: the pixel the position lies in)."""
        size, offset = self.block.size(), self.block.offset()
        x = mi.Int32(dr.floor(pos.x)) - offset.x
        y = mi.Int32(dr.floor(pos.y)) - offset.y
        return mi.UInt32(y * size.x + x)

    def scale(self):
        """Per pixel, 1 / the filter weights of all samples (0 where none), as NumPy."""
        weight = np.array(self.block.tensor())[..., -1].reshape(-1)
        return np.where(weight > 0, 1.0 / np.where(weight > 0, weight, 1.0), 0.0).astype(np.float32)

    def prepare(self, rec, beta, pos):
        """Turn one pass's records into splats, sorted by bin within tiles of pixels."""
        pixel = self.pixel_of(pos)
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
        scale = mi.Float(self.scale())
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
