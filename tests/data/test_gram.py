"""The one Gram matrix (data.gram): against float64 references, centred and not, in each feature space."""

import numpy as np
import pytest

from mitsuba_manifold.data import database, gram
from mitsuba_manifold.manifold import pruning, space


def test_gram_matches_float64_reference_with_chrome_like_peaks():
    rng = np.random.default_rng(0)
    n, d = 6, 50000
    tables = rng.uniform(0, 2e-3, (n, d)).astype(np.float32)      # diffuse-like 1e-3 values
    peaks = rng.choice(d, 20, replace=False)
    tables[0, peaks] = 1e4                                       # chrome-like peaks
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
    assert np.array_equal(S_both, S_log) and np.array_equal(G, pruning.raw_gram(tables))   # one pass, same sums
    with pytest.raises(ValueError, match="features"):
        Stub.gram(Stub(), names=list("abcdef"), tables=tables, features="sqrt")


def test_one_pass_gives_every_gram_the_package_uses():
    rng = np.random.default_rng(1)
    bins = 5000
    tables = rng.uniform(0, 3, (5, 3 * bins)).astype(np.float32)
    cos = rng.uniform(0, 1, bins)
    T = tables.astype(np.float64)
    for features, F in [("raw", T), ("log", np.log1p(T)), ("coslog", np.log1p(T * np.tile(cos, 3)))]:
        g = gram.gram(tables, features, centre=False, cos=cos, block=1024)
        assert g.mean is None and g.raw is None
        np.testing.assert_allclose(g.S, F @ F.T, rtol=1e-12)
        Z = F - F.mean(axis=0)
        c = gram.gram(tables, features, raw=True, cos=cos, block=1024)
        np.testing.assert_allclose(c.S, Z @ Z.T, rtol=1e-9, atol=1e-9 * np.abs(Z @ Z.T).max())
        np.testing.assert_allclose(c.mean, F.mean(axis=0), rtol=1e-6)
        assert np.array_equal(c.raw, pruning.raw_gram(tables, block=1024))
    assert np.array_equal(space.feature_gram(tables, "coslog", cos), gram.gram(tables, "coslog", centre=False, cos=cos).S)
    with pytest.raises(ValueError, match="`cos`"):
        gram.gram(tables, "coslog")
