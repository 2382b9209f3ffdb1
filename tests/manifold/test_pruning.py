"""Pruning: the "image" rule's bounds (albedo per channel, cosine-weighted table error) hold on
hypothesis-drawn weights, against the tables themselves; the "raw-l2" rule is the previous
release's; the report; manifold files without the new derived arrays still load and prune."""

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mitsuba_manifold.data.database import Database, albedo_weights
from mitsuba_manifold.manifold import pruning
from mitsuba_manifold.manifold.model import InputError, Manifold

SETTINGS = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)


@pytest.fixture(scope="module")
def default(small_manifold):
    m = Manifold.load(small_manifold)
    m.tables()
    return m


@pytest.fixture(scope="module")
def paper(small_manifold_paper):
    return Manifold.load(small_manifold_paper)


def _measure(m):
    """The float64 tables and the per-value cosine-weighted measure (the albedo quadrature, per channel)."""
    return m.tables().astype(np.float64), np.tile(albedo_weights(m.dims).reshape(-1), 3)


def _direct_changes(w, keep, w_kept, T, q):
    """Relative cosine-weighted L2 change, per-channel albedo change and raw L2 change, from the tables."""
    full = w @ T
    delta = w_kept @ T[keep] - full
    cos = np.sqrt((q * delta**2).sum() / (q * full**2).sum())
    albedo = lambda t: (t * q).reshape(3, -1).sum(axis=1)  # noqa: E731
    raw = np.linalg.norm(delta) / np.linalg.norm(full)
    return cos, np.abs(albedo(delta)) / np.maximum(np.abs(albedo(full)), pruning.ALBEDO_FLOOR), raw


def _weights(values, affine):
    w = np.asarray(values, dtype=np.float64)
    if affine:
        w = w - w.mean() + 1.0 / len(w) + 0.3 * w  # weights of both signs, summing to 1
    return w / w.sum() if abs(w.sum()) > 1e-3 else None


@SETTINGS
@given(
    values=st.lists(st.floats(0, 1), min_size=8, max_size=8),
    affine=st.booleans(),
    budget=st.floats(1e-3, 0.5),
    sparse=st.integers(0, 6),
)
def test_image_rule_bounds_hold_on_drawn_weights(default, values, affine, budget, sparse):
    w = _weights(values, affine)
    if w is None:
        return
    w[:sparse] = np.where(np.arange(sparse) % 2 == 0, 0.0, w[:sparse])  # some exact zeros
    if abs(w.sum()) < 1e-3:
        return
    keep, w_kept, dropped = default.prune(w, budget)
    assert len(keep) >= 1 and np.all(np.diff(keep) > 0)
    assert w_kept.sum() == pytest.approx(w.sum(), rel=1e-12, abs=1e-12)
    assert dropped == pytest.approx(np.abs(w).sum() - np.abs(w[keep]).sum(), abs=1e-12)
    assert not set(np.flatnonzero(w == 0)) & set(keep) or len(keep) == 1
    cos, albedo, raw = _direct_changes(w, keep, w_kept, *_measure(default))
    assert (
        cos <= budget * (1 + 1e-6) + 1e-9 and raw <= pruning.RAW_SHARE * budget * (1 + 1e-6) + 1e-9
    )
    assert (albedo <= pruning.ALBEDO_SHARE * budget * (1 + 1e-6) + 1e-9).all()
    report = default.prune_report(w, budget)
    assert report.keep == tuple(keep) and report.within and report.rule == "image"
    assert report.cos_error == pytest.approx(cos, rel=1e-6, abs=1e-9)
    assert report.raw_error == pytest.approx(raw, rel=1e-6, abs=1e-9)
    np.testing.assert_allclose(report.albedo_change, albedo, rtol=1e-6, atol=1e-9)


@settings(max_examples=80, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 60),
    budget=st.floats(1e-4, 0.3),
    affine=st.booleans(),
    share=st.sampled_from([0.5, 0.1, 2.0]),
    raw_share=st.sampled_from([1.0, 3.0, np.inf]),
)
def test_image_rule_on_many_materials_is_within_bounds_and_greedy_to_the_end(
    seed, n, budget, affine, share, raw_share
):
    """Spiky and dull synthetic tables: both bounds hold, exactly (no Gram matrix needed to check
    them), and no kept material could be dropped as well (the search stops only when it must)."""
    rng = np.random.default_rng(seed)
    bins = 200
    T = rng.uniform(0, 1, (n, 3 * bins)) * rng.uniform(0.01, 1, (n, 1))
    T[rng.random(n) < 0.3, :3] *= 1e4  # specular peaks in a few bins
    q = np.tile(rng.uniform(0, 1, bins) * np.r_[1e-6, np.ones(bins - 1)], 3)
    C = (T * q) @ T.T
    A = (T * q).reshape(n, 3, bins).sum(axis=2)
    w = rng.dirichlet(np.full(n, 0.3))
    if affine:
        w = w + rng.normal(0, 0.2 / n, n)
        w /= w.sum()
    G = T @ T.T
    keep, w_kept, _ = pruning.prune_image(w, C, A, budget, share, G=G, raw_share=raw_share)
    cos, albedo, raw = _direct_changes(w, keep, w_kept, T, q)
    assert len(keep) >= 1 and w_kept.sum() == pytest.approx(w.sum(), rel=1e-12)
    assert (
        cos <= budget * (1 + 1e-6) + 1e-12 and (albedo <= share * budget * (1 + 1e-6) + 1e-12).all()
    )
    assert raw <= raw_share * budget * (1 + 1e-6) + 1e-12
    if len(keep) > 1:
        kept = np.zeros(n, dtype=bool)
        kept[keep] = True
        fewer = np.repeat(kept[None], len(keep), axis=0)
        fewer[np.arange(len(keep)), keep] = False  # each row drops one more
        over = (
            (pruning.errors(w, fewer, C) > budget * (1 - 1e-8))
            | (pruning.errors(w, fewer, G) > raw_share * budget * (1 - 1e-8))
            | (pruning.albedo_changes(w, fewer, A) > share * budget * (1 - 1e-8)).any(axis=1)
        )
        assert over.all()


def test_budget_zero_keeps_every_nonzero_weight_and_one_material_is_always_kept(default):
    w = np.r_[0.5, 0.0, 0.25, 0.0, 0.25, 0.0, 0.0, 0.0]
    for rule in pruning.RULES:
        assert default.prune(w, 0.0, rule=rule).keep.tolist() == [0, 2, 4]
    one = np.eye(default.n)[3]
    assert default.prune(one, 0.4).keep.tolist() == [3]
    keep, w_kept, _ = pruning.prune_image(
        np.zeros(default.n), default.cos_gram, default.albedos, 0.1
    )
    assert len(keep) == 1 and w_kept.tolist() == [0.0]
    with pytest.raises(InputError, match="`rule`.*'image'"):
        default.prune(w, 0.01, rule="l2")
    with pytest.raises(InputError, match="`prune`"):
        default.prune(w, 1.0)


def _old_rule(w, T, budget):
    """The previous release's rule from the tables, prefix by prefix (a reference, not the code)."""
    n = len(w)
    order = np.argsort(np.abs(w) * np.linalg.norm(T, axis=1), kind="stable")
    full = w @ T
    best = int(np.count_nonzero(w == 0))
    for k in range(n):
        kept = order[k:]
        if abs(w[kept].sum()) > 0:
            err = np.linalg.norm(
                w[kept] * (w.sum() / w[kept].sum()) @ T[kept] - full
            ) / np.linalg.norm(full)
            if err <= budget:
                best = max(best, k)
    return np.sort(order[min(best, n - 1) :])


def test_raw_l2_rule_is_the_previous_release_s(paper):
    T = paper.tables().astype(np.float64)
    rng = np.random.default_rng(4)
    X = paper.latent.mean(0) + rng.normal(scale=0.6, size=(25, paper.q))
    for w, budget in zip(paper.weights(X).w, np.geomspace(1e-3, 0.2, 25)):
        keep, w_kept, _ = paper.prune(w, budget, rule="raw-l2")
        assert keep.tolist() == _old_rule(w, T, budget).tolist()
        assert np.array_equal(keep, pruning.prune(w, paper.table_gram, budget)[0])
        err = np.linalg.norm(w_kept @ T[keep] - w @ T) / np.linalg.norm(w @ T)
        assert err <= budget + 1e-9 and paper.prune_error(w, keep, rule="raw-l2") == pytest.approx(
            err, abs=1e-7
        )
        assert paper.prune_report(w, budget, rule="raw-l2").raw_error == pytest.approx(
            err, abs=1e-7
        )


def test_interpolate_and_combine_prune_with_the_image_rule_by_default(default):
    T, q = _measure(default)
    x = default.latent[:2].mean(axis=0) + 0.05
    w = default.weights(x).w
    table, keep, dropped = default.interpolate(x)
    assert keep.tolist() == default.prune(w).keep.tolist() and len(keep) < default.n
    full = default.interpolate(x, prune=0.0).table
    albedo = lambda t: t.reshape(3, -1) @ q[: q.size // 3]  # noqa: E731
    assert (np.abs(albedo(table) - albedo(full)) <= 0.005 * albedo(full) * (1 + 1e-4)).all()
    raw = default.combine(w, rule="raw-l2")
    assert raw.keep.tolist() == default.prune(w, rule="raw-l2").keep.tolist()


def test_the_report_says_what_was_kept_and_the_bounds_reached(default):
    w = default.weights(default.latent[:3].mean(axis=0)).w
    r = default.prune_report(w)
    assert (
        isinstance(r, pruning.PruneReport)
        and r.rule == "image"
        and r.budget == pruning.DEFAULT_PRUNE
    )
    assert (
        r.albedo_budget == pytest.approx(0.005) and r.n == default.n and r.kept == len(r.keep) >= 1
    )
    assert r.names == tuple(default.names[i] for i in r.keep)
    assert r.cos_error == pytest.approx(default.prune_error(w, r.keep), abs=1e-12) and r.within
    text = str(r)
    assert f"{r.kept} of {default.n} materials kept" in text and "albedo change R/G/B" in text
    assert "cosine-weighted table error" in text and "raw L2 error" in text
    assert r.raw_budget == r.cos_budget == r.budget and r.raw_error <= r.raw_budget
    assert "(<= 0.5%)" in text and "(<= 1%)" in text
    late = pruning.PruneReport(
        "image", 0.01, 0.005, 0.01, 0.01, (0,), 2, 0.5, (0.006, 0.0, 0.0), 0.001, 0.002
    )
    assert not late.within
    old = default.prune_report(w, rule="raw-l2")
    assert (
        old.albedo_budget is None
        and old.cos_budget is None
        and old.raw_budget == 0.01
        and old.within
    )


def _rewrite_without(path, out, names):
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files if k not in names}
    np.savez(out, **arrays)


def test_manifold_files_without_the_cosine_gram_or_albedos_load_and_prune_the_same(
    small_manifold, tmp_path
):
    fresh = Manifold.load(small_manifold)
    assert fresh.cos_gram is not None  # stored by the fit
    with np.load(small_manifold, allow_pickle=False) as z:
        assert "cos_gram" in z.files and json.loads(str(z["meta"]))["version"] == 2
    X = fresh.latent.mean(0) + np.random.default_rng(5).normal(scale=0.5, size=(10, fresh.q))
    expected = [fresh.prune(w).keep.tolist() for w in fresh.weights(X).w]
    for missing in (["cos_gram"], ["cos_gram", "table_gram", "albedos"]):
        path = tmp_path / f"m{len(missing)}.npz"
        _rewrite_without(small_manifold, path, missing)
        old = Manifold.load(path)
        assert old.cos_gram is None and (old.albedos is None) == ("albedos" in missing)
        assert [old.prune(w).keep.tolist() for w in old.weights(X).w] == expected
        np.testing.assert_allclose(old.cos_gram, fresh.cos_gram, rtol=1e-12)
        np.testing.assert_allclose(old.albedos, fresh.albedos, rtol=1e-12)
        np.testing.assert_allclose(old.table_gram, fresh.table_gram, rtol=1e-12)
        old.save(tmp_path / "again.npz")  # the computed arrays are saved with it
        with np.load(tmp_path / "again.npz", allow_pickle=False) as z:
            assert {"cos_gram", "table_gram", "albedos"} <= set(z.files)
    again = Manifold.load(tmp_path / "m1.npz")  # computed once per database: cached
    assert [again.prune(w).keep.tolist() for w in again.weights(X).w] == expected
    assert again._tables is None and np.array_equal(again.cos_gram, old.cos_gram)


def test_cosine_gram_is_the_tables_in_the_measure_light_sees(default, small_db):
    T, q = _measure(default)
    np.testing.assert_allclose(default.cos_gram, (T * q) @ T.T, rtol=1e-10)
    np.testing.assert_allclose(
        default.albedos, Database(small_db, default.names).albedo(), rtol=1e-6
    )


def test_repeated_pruning_gives_the_same_answer_in_arrays_of_its_own(default):
    """The last answers are kept (the explorer prunes one point three times): the same answer
    for the same weights, budget and rule, never one of other weights, and arrays the caller
    may change without changing the next answer."""
    rng = np.random.default_rng(3)
    w = rng.dirichlet(np.ones(default.n))
    first = default.prune(w, 0.05)
    first.keep[:] = -1
    first.w_kept[:] = np.nan
    again = default.prune(w, 0.05)
    store, db = default._store, default.database
    fresh = pruning.prune_image(
        w, store.cosine_gram(db), store.albedo(db), 0.05, G=store.raw_gram(db)
    )
    np.testing.assert_array_equal(again.keep, fresh[0])
    np.testing.assert_allclose(again.w_kept, fresh[1])
    other = default.prune(np.roll(w, 1), 0.05)
    assert not np.array_equal(other.w_kept, again.w_kept) or not np.array_equal(
        other.keep, again.keep
    )
    assert len(default.prune(w, 0.0).keep) == np.count_nonzero(w)
