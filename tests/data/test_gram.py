"""The one Gram matrix (data.gram): against float64 references, centred and not, in each feature space."""

import numpy as np
import pytest

from mitsuba_manifold.data import database, gram
from mitsuba_manifold.manifold import pruning, space


def test_gram_matches_float64_reference_with_chrome_like_peaks():
    rng = np.random.default_rng(0)
    n, d = 6, 50000
    tables = rng.uniform(0, 2e-3, (n, d)).astype(np.float32)  # diffuse-like 1e-3 values
    peaks = rng.choice(d, 20, replace=False)
    tables[0, peaks] = 1e4  # chrome-like peaks
    tables[1, peaks[:5]] = 3e3
    ref = tables.astype(np.float64)
    ref -= ref.mean(axis=0)
    S_ref = ref @ ref.T

    class Stub(database.Database):
        def __init__(self):
            pass

    mean, S = Stub.gram(Stub(), names=list("abcdef"), tables=tables, block=4096)
    assert np.allclose(mean, tables.astype(np.float64).mean(axis=0), rtol=1e-6)
    # small entries (diffuse-diffuse pairs) must be accurate too, not only the huge ones
    assert np.allclose(S, S_ref, rtol=1e-9, atol=1e-9 * np.abs(S_ref[2:, 2:]).max())
    _, S_log = Stub.gram(Stub(), names=list("abcdef"), tables=tables, features="log")
    z = np.log1p(tables.astype(np.float64))
    z -= z.mean(axis=0)
    assert np.allclose(S_log, z @ z.T, rtol=1e-9)
    _, S_both, G = Stub.gram(Stub(), names=list("abcdef"), tables=tables, features="log", raw=True)
    assert np.array_equal(S_both, S_log) and np.array_equal(
        G, pruning.raw_gram(tables)
    )  # one pass, same sums
    with pytest.raises(ValueError, match="features"):
        Stub.gram(Stub(), names=list("abcdef"), tables=tables, features="sqrt")


def test_one_pass_gives_every_gram_the_package_uses():
    rng = np.random.default_rng(1)
    bins = 5000
    tables = rng.uniform(0, 3, (5, 3 * bins)).astype(np.float32)
    cos = rng.uniform(0, 1, bins)
    T = tables.astype(np.float64)
    for features, F in [
        ("raw", T),
        ("log", np.log1p(T)),
        ("coslog", np.log1p(T * np.tile(cos, 3))),
    ]:
        g = gram.gram(tables, features, centre=False, cos=cos, block=1024)
        assert g.mean is None and g.raw is None
        np.testing.assert_allclose(g.S, F @ F.T, rtol=1e-12)
        Z = F - F.mean(axis=0)
        c = gram.gram(tables, features, raw=True, cos=cos, block=1024)
        np.testing.assert_allclose(c.S, Z @ Z.T, rtol=1e-9, atol=1e-9 * np.abs(Z @ Z.T).max())
        np.testing.assert_allclose(c.mean, F.mean(axis=0), rtol=1e-6)
        assert np.array_equal(c.raw, pruning.raw_gram(tables, block=1024))
    assert np.array_equal(
        space.feature_gram(tables, "coslog", cos),
        gram.gram(tables, "coslog", centre=False, cos=cos).S,
    )
    with pytest.raises(ValueError, match="`cos`"):
        gram.gram(tables, "coslog")


def test_cosine_weighted_gram_comes_from_the_same_pass():
    """``T diag(q) T^T`` (the "image" pruning rule's measure) beside the fit's Gram, in one pass."""
    rng = np.random.default_rng(2)
    bins = 3000
    tables = rng.uniform(0, 3, (4, 3 * bins)).astype(np.float32)
    tables[0, :7] = 1e5  # peaks in bins of tiny measure
    q = rng.uniform(0, 1e-3, bins)
    q[:7] = 1e-9
    T = tables.astype(np.float64)
    g = gram.gram(tables, "log", centre=True, raw=True, weights=q, block=1000)
    np.testing.assert_allclose(g.weighted, (T * np.tile(q, 3)) @ T.T, rtol=1e-12)
    assert np.array_equal(g.raw, pruning.raw_gram(tables, block=1000))
    assert np.array_equal(
        g.S, gram.gram(tables, "log", centre=True, block=1000).S
    )  # the fit's Gram unchanged
    G, C = pruning.cos_grams(tables, q, block=1000)
    assert np.array_equal(G, g.raw) and np.array_equal(C, g.weighted)
    assert gram.gram(tables, "raw").weighted is None
    with pytest.raises(ValueError, match="`weights`.*3000"):
        gram.gram(tables, "raw", weights=q[:-1])


def test_worker_threads_give_the_one_thread_sums_bit_for_bit(monkeypatch):
    """The blocks' products are added in block order whatever the number of workers (a fit
    whose optimiser runs to its iteration limit moves with any change of ``S``'s last bit).
    """
    rng = np.random.default_rng(3)
    bins = 2500
    tables = rng.lognormal(-3, 2, (7, 3 * bins)).astype(np.float32)
    q = rng.uniform(0, 1e-3, bins)
    runs = []
    for workers in (1, 2, 5):
        monkeypatch.setattr(gram, "workers_for", lambda n, w=workers: w)
        runs.append(gram.gram(tables, "log", raw=True, weights=q, block=700))
    for other in runs[1:]:
        for field in ("S", "mean", "raw", "weighted", "sums"):
            assert np.array_equal(getattr(other, field), getattr(runs[0], field)), field
    # and the same as a plain serial NumPy loop over the blocks
    S = np.zeros((7, 7))
    for s in range(0, 3 * bins, 700):
        z = np.log1p(tables[:, s : s + 700].astype(np.float64))
        z -= z.mean(axis=0)
        S += z @ z.T
    assert np.array_equal(runs[0].S, 0.5 * (S + S.T))


def test_weighted_sums_per_channel_across_blocks_that_straddle_channels():
    """The albedo-like sums ``T_c q`` per channel, with blocks that span a channel's end."""
    rng = np.random.default_rng(4)
    bins = 1001
    tables = rng.uniform(0, 5, (4, 3 * bins)).astype(np.float32)
    q = rng.uniform(0, 1, bins)
    ref = tables.astype(np.float64).reshape(4, 3, bins) @ q
    for block in (64, 1000, 1002, 5000):
        g = gram.gram(tables, "raw", centre=False, weights=q, block=block)
        np.testing.assert_allclose(g.sums, ref, rtol=1e-12)
    # negative weights: the weighted Gram by its general product
    q[::7] *= -1
    g = gram.gram(tables, "raw", centre=False, weights=q, block=300)
    T = tables.astype(np.float64)
    np.testing.assert_allclose(g.weighted, (T * np.tile(q, 3)) @ T.T, rtol=1e-10)
    np.testing.assert_allclose(g.sums, T.reshape(4, 3, bins) @ q, rtol=1e-10)
