"""The splats of one pass of :func:`~.onepass.render_onepass`, turned into every material's image.

A sample's vertex on the target becomes two *splats* (light connection, sampled direction):
a pixel, a MERL bin, an RGB amplitude ``a``; a material adds ``a * table(bin)`` to the pixel,
so the images are a sparse product ``(pixels x bins) @ (bins x materials)``.

The film's reconstruction filter enters as it does in Mitsuba's film: a sample at film position
``s`` adds ``r(p_x + 1/2 - s_x) r(p_y + 1/2 - s_y) L`` to every pixel ``p`` of its footprint, and
each pixel is divided by the sum of those weights over all samples (:class:`FilterTaps`). Since a
material's image is linear in each sample's ``L``, each splat is put into every pixel of its
sample's footprint with that weight (one pixel of weight 1 for the box filter), and every
material's image is the film's.
:class:`TableSplats` computes the product directly (nearest lookups), :class:`FilterSplats`
through image blocks with the film's filter (each material evaluated by its BSDF).
"""

import drjit as dr
import mitsuba as mi
import numpy as np

from ..plugin.lookups import merl_angles, merl_bin

#: Materials per packet of the table product (Dr.Jit packet gathers of 16 contiguous floats).
PACKET = 16
#: Most bytes of per-pixel sums one table kernel holds (Expand mode keeps a copy per thread).
_SUM_BYTES = 1 << 28
_NO_BIN = 0xFFFFFFFF


class FilterTaps:
    """The pixels of an image block that a sample at film position ``pos`` adds to, and the
    filter's weight there, as ``ImageBlock.put`` computes them: the pixels ``p`` within
    ``n = ceil(radius - 1/2)`` of the sample's, of weight ``r(p_x + 1/2 - pos_x) r(p_y + 1/2 - pos_y)``
    (``r``: the film's filter; pixels outside the block dropped); the box filter adds 1 to the
    sample's pixel. The block must not normalise its samples and have no border (a film's block).
    """

    def __init__(self, block, rfilter):
        self.size, self.offset = block.size(), block.offset()
        self.rfilter = rfilter
        self.box = rfilter.is_box_filter()
        self.n = 0 if self.box else int(np.ceil(float(rfilter.radius()) - 0.5))

    @property
    def count(self):
        """Taps per sample."""
        return (2 * self.n + 1) ** 2

    def taps(self, pos):
        """``[(pixel, weight)]``, one pair per tap: each sample's pixel row (``y * width + x``)
        and weight (``None`` for the box filter's single tap: 1; 0 where the tap leaves the block).
        """
        x0 = mi.Int32(dr.floor(pos.x)) - self.offset.x
        y0 = mi.Int32(dr.floor(pos.y)) - self.offset.y
        if self.box:
            return [(mi.UInt32(y0 * self.size.x + x0), None)]
        out = []
        for dy in range(-self.n, self.n + 1):
            y = y0 + dy
            wy = self.rfilter.eval(mi.Float(y + self.offset.y) + 0.5 - pos.y)
            for dx in range(-self.n, self.n + 1):
                x = x0 + dx
                wx = self.rfilter.eval(mi.Float(x + self.offset.x) + 0.5 - pos.x)
                inside = (x >= 0) & (y >= 0) & (x < self.size.x) & (y < self.size.y)
                w = dr.select(inside, wx * wy, 0.0)
                out.append((mi.UInt32(dr.select(inside, y * self.size.x + x, 0)), w))
        return out


def expand(taps, idx):
    """The splats of samples ``idx`` (UInt32) in every pixel of their footprint: ``(take, pixel,
    weight)`` per tap with a weight somewhere, ``take`` indexing ``idx`` (None: all of them) and
    ``weight`` None for a weight of 1.
    """
    out = []
    for pixel, weight in taps:
        pix = dr.gather(mi.UInt32, pixel, idx)
        if weight is None:
            out.append((None, pix, None))
            continue
        w = dr.gather(mi.Float, weight, idx)
        take = dr.compress(w != 0)
        if dr.width(take) == 0:
            continue
        out.append((take, dr.gather(mi.UInt32, pix, take), dr.gather(mi.Float, w, take)))
    return out


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
            t = dr.gather(
                mi.ArrayXf,
                rows,
                (b * 3 + c) * row_packets + kb0 + kb,
                shape=(PACKET, dr.width(lane)),
            )
            dr.scatter_add(
                sums,
                dr.maximum(t, 0.0) * data[c + 1],
                (q * 3 + c) * nb + kb,
                mode=dr.ReduceMode.Expand,
            )
        dr.eval(sums)
    finally:
        dr.set_expand_threshold(threshold)


class TableSplats:
    """The splats of :func:`render_onepass` as per-pixel sums ``sum a * table(bin)`` of every
    material: nearest lookups, each splat in every pixel of its sample's filter footprint
    (:class:`FilterTaps`).

    Sums are kept per chunk of materials, laid out ``(pixels, 3, materials padded to
    PACKET)``. When a chunk's sums of the whole image, copied once per thread, exceed
    ``_SUM_BYTES``, the splats are processed in tiles of pixels into smaller sums first.
    """

    def __init__(self, block, rows, names, chunks, dims, rfilter):
        self.block, self.names, self.dims = block, names, dims
        self.filter = FilterTaps(block, rfilter)
        self.n_pad = int(rows.shape[2])
        self.rows = mi.Float(np.asarray(rows).reshape(-1))  # maps the cached file, no copy
        self.pixels = int(dr.prod(block.size()))
        self.packets = [(k0 // PACKET, -(-k1 // PACKET)) for k0, k1 in chunks]
        self.chunks = chunks
        self.sums = [
            dr.zeros(mi.Float, self.pixels * 3 * (b1 - b0) * PACKET) for b0, b1 in self.packets
        ]
        widest = max(b1 - b0 for b0, b1 in self.packets) * PACKET
        self.tile = max(1, _SUM_BYTES // (12 * widest * max(1, dr.thread_count())))
        self.tiles = []

    def taps(self, pos):
        """Each sample's pixels in the sums and their filter weights (:meth:`FilterTaps.taps`)."""
        return self.filter.taps(pos)

    def scale(self):
        """Per pixel, 1 / the filter weights of all samples (0 where none), as NumPy."""
        weight = np.array(self.block.tensor())[..., -1].reshape(-1)
        return np.where(weight > 0, 1.0 / np.where(weight > 0, weight, 1.0), 0.0).astype(np.float32)

    def prepare(self, rec, beta, pos):
        """Turn one pass's records into splats, sorted by bin within tiles of pixels."""
        taps = self.taps(pos)
        pixel = taps[0][0]
        keys, amps = [], []
        for wo, a in ((rec["wo_nee"], rec["e_nee"]), (rec["wo"], rec["g"])):
            a = beta * a * wo.z
            ok = (rec["wi"].z > 0) & (wo.z > 0) & dr.any(a != 0)
            keys.append(dr.select(ok, merl_bin(*merl_angles(rec["wi"], wo), self.dims), _NO_BIN))
            amps.append(a)
        dr.eval(self.block.tensor(), taps, keys, amps)
        # Both splats of every sample in sample order (so in pixel order), compacted.
        j = dr.arange(mi.UInt32, 2 * dr.width(pixel))
        key = dr.select(
            (j & 1) != 0,
            dr.gather(mi.UInt32, keys[1], j >> 1),
            dr.gather(mi.UInt32, keys[0], j >> 1),
        )
        idx = dr.compress(key != _NO_BIN)
        self.tiles = []
        if dr.width(idx) == 0:
            return
        second = (idx & 1) != 0
        amp = dr.select(
            second,
            dr.gather(mi.Color3f, amps[1], idx >> 1),
            dr.gather(mi.Color3f, amps[0], idx >> 1),
        )
        key = dr.gather(mi.UInt32, key, idx)
        if self.filter.box:
            pix = dr.gather(mi.UInt32, pixel, idx >> 1)
        else:  # every splat in each pixel of its footprint, weighted; then in pixel order
            parts = expand(taps, idx >> 1)
            pix = dr.concat([p for _, p, _ in parts])
            amp = mi.Color3f(
                *(
                    dr.concat([dr.gather(mi.Float, amp[c], t) * w for t, _, w in parts])
                    for c in range(3)
                )
            )
            key = dr.concat([dr.gather(mi.UInt32, key, t) for t, _, _ in parts])
            order = mi.UInt32(np.argsort(pix.numpy(), kind="stable").astype(np.uint32))
            pix, amp, key = (dr.gather(type(v), v, order) for v in (pix, amp, key))
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
            splats = mi.Vector4f(
                dr.reinterpret_array(mi.Float, dr.gather(mi.UInt32, key, order)), a.x, a.y, a.z
            )
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
            out = dr.gather(mi.Float, sums, r * width + k + (k0 - kb0 * PACKET)) * dr.gather(
                mi.Float, scale, p
            )
            out = out.numpy().reshape((k1 - k0,) + shape)
            for k, name in enumerate(self.names[k0:k1]):
                images[name] = out[k]
        return images


class FilterSplats:
    """The splats of :func:`render_onepass` put into image blocks with the film's filter,
    each material evaluated at them (``nearest``: one gather from its table; ``linear``: the
    BSDF's own ``eval``).
    """

    def __init__(self, film, block, names, chunks, db, path, options, several_passes):
        self.film, self.block, self.names, self.chunks = film, block, names, chunks
        self.db, self.path, self.options = db, path, options
        self.dims = tuple(int(d) for d in db.dims)
        bins = int(np.prod(self.dims))
        self.nearest = options["interpolation"] == "nearest"
        self.blocks = [
            mi.ImageBlock(
                block.size(),
                block.offset(),
                3 * (k1 - k0),
                film.rfilter(),
                border=block.has_border(),
                normalize=block.normalize(),
                coalesce=block.coalesce(),
            )
            for k0, k1 in chunks
        ]
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
            data = [
                dr.maximum(
                    dr.gather(
                        mi.Float,
                        mi.Float(
                            np.ascontiguousarray(self.db.reflectance(n), np.float32).reshape(-1)
                        ),
                        self.interleave,
                    ),
                    0.0,
                )
                for n in self.names[k0:k1]
            ]
            dr.eval(data)
        else:
            data = [
                mi.load_dict(
                    {
                        "type": "manifold_brdf",
                        "manifold": self.path,
                        "material": n,
                        "sampling": "cosine",
                        **self.options,
                    }
                )
                for n in self.names[k0:k1]
            ]
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
            order = np.argsort(key, kind="stable")[: int(np.count_nonzero(key != _NO_BIN))]
            if order.size == 0:
                continue
            idx = mi.UInt32(order.astype(np.uint32))
            pick = lambda v, idx=idx: dr.gather(type(v), v, idx)  # noqa: E731
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
        normalised by the filter weights of all samples.
        """
        head = np.array(self.block.tensor())
        images = {}
        for (k0, k1), block in zip(self.chunks, self.blocks):
            aovs = [f"m{k}.{c}" for k in range(k1 - k0) for c in "RGB"]
            film.prepare(aovs)
            merged = np.concatenate([head, np.array(block.tensor())], axis=-1)
            film.put_block(
                mi.ImageBlock(
                    mi.TensorXf(merged),
                    self.block.offset(),
                    film.rfilter(),
                    border=self.block.has_border(),
                    normalize=self.block.normalize(),
                    coalesce=self.block.coalesce(),
                )
            )
            img = np.array(film.develop(), dtype=np.float32)
            start = img.shape[-1] - len(aovs)
            for k, name in enumerate(self.names[k0:k1]):
                images[name] = img[..., start + 3 * k : start + 3 * k + 3].copy()
        return images
