"""The Manifold: weights, exact reproduction, far field, save/load and mismatches."""

import gc
import os
import shutil
import weakref

import numpy as np
import pytest

from mitsuba_manifold.data import database, merl
from mitsuba_manifold.data.database import Database
from mitsuba_manifold.errors import UnavailableError
from mitsuba_manifold.manifold.model import InputError, Manifold


@pytest.fixture(scope="module")
def fitted(small_manifold_paper):
    """The paper's formulation: GP weights of Eq. 4."""
    return Manifold.load(small_manifold_paper)


def test_weights_are_affine_and_match_mean_plus_bZ(fitted, small_db):
    rng = np.random.default_rng(0)
    x = fitted.latent.mean(0) + rng.normal(scale=0.5, size=(7, fitted.q))
    b, w = fitted.weights(x)
    assert b.shape == w.shape == (7, fitted.n)
    assert np.allclose(w.sum(axis=1), 1.0, atol=1e-12)
    tables = Database(small_db, fitted.names).stack().astype(np.float64)
    mean = tables.mean(axis=0)
    Z = tables - mean
    for k in range(3):
        assert np.allclose(
            w[k] @ tables, mean + b[k] @ Z, rtol=1e-9, atol=1e-9 * np.abs(tables).max()
        )
    # single point gives 1-D arrays, equal to the batched row
    b0, w0 = fitted.weights(x[0])
    assert np.allclose(w0, w[0]) and np.allclose(b0, b[0])


def test_training_materials_are_reproduced_exactly(fitted, small_db):
    db = Database(small_db)
    for i, name in enumerate(fitted.names):
        b, w = fitted.weights(fitted.latent[i])
        assert np.array_equal(w, np.eye(fitted.n)[i])
        table, keep, dropped = fitted.interpolate(fitted.latent[i])
        assert keep.tolist() == [i] and dropped == 0
        assert np.array_equal(table, np.asarray(db.reflectance(name)))
        assert fitted.variance(fitted.latent[i]) == pytest.approx(0.0, abs=1e-9)
    assert np.allclose(fitted.albedo(fitted.latent), fitted.albedos, atol=1e-12)


def test_discontinuity_is_the_jump_next_to_a_training_point(fitted):
    jumps = []
    for i in range(fitted.n):
        _, w_near = fitted.weights(fitted.latent[i] + 1e-9)
        jumps.append(np.abs(w_near - np.eye(fitted.n)[i]).sum())
    assert max(jumps) == pytest.approx(fitted.discontinuity(), rel=1e-4, abs=1e-7)


def test_far_field_tends_to_the_mean(fitted):
    for dist in [1e3, 1e6]:
        x = fitted.latent.mean(0) + dist
        b, w = fitted.weights(x)
        assert np.all(np.isfinite(w)) and np.allclose(b, 0, atol=1e-12)
        assert np.allclose(w, 1.0 / fitted.n)
        table, keep, _ = fitted.interpolate(x)
        assert np.allclose(table, fitted.mean(), rtol=1e-5, atol=1e-6 * np.abs(table).max())
        assert fitted.variance(x) == pytest.approx(1.0 + fitted.noise)


def test_interpolated_albedo_uses_linearity(fitted):
    x = fitted.latent[:2].mean(axis=0)
    table, _, _ = fitted.interpolate(x, prune=0.0)
    q = database.albedo_weights(table.shape[1:]).reshape(-1)
    assert np.allclose(fitted.albedo(x), table.reshape(3, -1) @ q, rtol=1e-4)


def test_pruning_reports_dropped_weight(fitted):
    x = fitted.latent[0] + 0.05
    _, w = fitted.weights(x)
    keep, w_kept, dropped = fitted.prune(w, 0.05)
    assert dropped == pytest.approx(np.abs(w).sum() - np.abs(w[keep]).sum())
    assert w_kept.sum() == pytest.approx(w.sum())
    full, keep0, d0 = fitted.combine(w, prune=0.0)
    assert d0 == 0 and len(keep0) == fitted.n
    pruned, _, _ = fitted.combine(w, prune=0.05)
    assert np.abs(pruned - full).max() <= 1.1 * dropped * np.abs(fitted.tables()).max()


def test_combine_is_the_weighted_sum_of_the_tables_to_float32_rounding(
    small_manifold_paper, small_db
):
    """Every way combine sums (one product over all tables in memory, a sum over the few kept
    rows in memory, the kept tables read from the database) gives ``sum_i w_i table_i`` to
    float32 rounding.
    """
    memory, disk = Manifold.load(small_manifold_paper), Manifold.load(small_manifold_paper)
    tables = memory.tables().astype(np.float64)
    assert disk._tables is None
    _, w = memory.weights(memory.latent[0] + 0.05)
    scale = np.abs(tables).max()
    for prune in (0.0, 0.2):
        pruned = memory.prune(w, prune)
        ref = pruned.w_kept @ tables[pruned.keep]
        for c in (memory.combine(w, prune=prune), disk.combine(w, prune=prune)):
            assert c.table.dtype == np.float32 and np.array_equal(c.keep, pruned.keep)
            assert np.abs(c.table.reshape(-1) - ref).max() <= 1e-6 * scale
    assert 2 * len(memory.prune(w, 0.2).keep) <= memory.n < 2 * len(memory.prune(w, 0.0).keep)
    assert disk._tables is None  # the kept tables were read, not all loaded


def test_save_load_round_trip_without_pickle(fitted, tmp_path):
    path = tmp_path / "m.npz"
    fitted.save(path)
    with np.load(path, allow_pickle=False) as z:
        assert all(z[k].dtype != object for k in z.files)
    m = Manifold.load(path)
    assert m.names == fitted.names and np.array_equal(m.latent, fitted.latent)
    assert m.hashes == fitted.hashes and m.q == fitted.q
    assert m.log_likelihood() == pytest.approx(fitted.info["log_likelihood"], rel=1e-9)
    x = fitted.latent.mean(0)
    assert np.array_equal(m.weights(x)[1], fitted.weights(x)[1])
    # ``path``: the former name of ``file`` (a path is a latent path here), still read
    with pytest.warns(DeprecationWarning, match=r"Manifold.save\(path=...\) is now spelled"):
        fitted.save(path=tmp_path / "old.npz")
    with pytest.warns(DeprecationWarning, match=r"Manifold.load\(path=...\) is now spelled"):
        again = Manifold.load(path=tmp_path / "old.npz")
    assert np.array_equal(again.latent, fitted.latent)
    assert Manifold.load(file=path).names == fitted.names


@pytest.mark.parametrize("name", ["albedos", "gram", "table_gram"])
def test_a_manifold_file_with_a_damaged_derived_array_is_refused(fitted, tmp_path, name):
    """NaN in the saved pruning Gram made the plugin drop nearly every material silently."""
    path = tmp_path / "m.npz"
    fitted.save(path)
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    arrays[name] = np.full_like(arrays[name], np.nan)
    np.savez(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match=f"its {name} array is damaged"):
        Manifold.load(tmp_path / "bad.npz")


def test_latent_points_of_the_wrong_kind_are_named(fitted):
    with pytest.raises(InputError, match="must be 2 numbers"):
        fitted.weights("0.3,-1.2")
    with pytest.raises(
        InputError, match=r"interpolate takes one latent point .* got shape \(2, 2\)"
    ):
        fitted.interpolate(np.zeros((2, 2)))
    with pytest.raises(InputError, match=r"2 coordinates, got shape \(\)"):
        fitted.weights(None)


def test_bad_inputs_give_clear_errors(fitted, small_db, tmp_path):
    with pytest.raises(InputError, match="2 coordinates"):
        fitted.weights([0.1, 0.2, 0.3])
    with pytest.raises(InputError, match="NaN"):
        fitted.weights([np.nan, 0.0])
    with pytest.raises(InputError, match="unknown material 'mithril'"):
        fitted.material_weights("mithril")
    with pytest.raises(InputError, match="sum to zero"):
        fitted.parse_weights("chrome:1, steel:-1")
    with pytest.raises(InputError, match="not 'name:number'"):
        fitted.parse_weights("chrome:abc")
    with pytest.raises(InputError, match="commas separate entries"):  # a comma forgotten
        fitted.parse_weights("chrome:0.4 steel:0.6")
    assert fitted.parse_weights("chrome:0.25, steel:0.75")[fitted.index("steel")] == 0.75
    with pytest.raises(InputError, match="chrome is named twice"):
        fitted.parse_weights("chrome:0.5, chrome:0.5")
    with pytest.raises(InputError, match="does not exist"):
        Manifold.load(tmp_path / "missing.npz")
    corrupt = tmp_path / "corrupt.npz"
    corrupt.write_bytes(b"PK\x03\x04 not really a zip")
    with pytest.raises(InputError, match="not a manifold .npz written by fit_manifold"):
        Manifold.load(corrupt)
    # a database whose table changed since the fit
    copy = tmp_path / "db"
    shutil.copytree(small_db, copy, ignore=shutil.ignore_patterns(".manifold-cache"))
    raw = merl.read_binary(copy / "chrome.binary")
    raw[raw > 0] *= 1.01
    merl.write_binary(copy / "chrome.binary", raw)
    with pytest.raises(InputError, match="chrome.*differs"):
        fitted.open_database(copy)
    fitted.open_database(copy, ["steel"])  # untouched tables still check out
    os.remove(copy / "steel.binary")
    with pytest.raises(InputError, match="no table for"):
        fitted.open_database(copy, ["steel"])


def test_files_that_are_not_manifolds_are_named_without_inviting_unsafe_loading(small_db, tmp_path):
    from PIL import Image

    Image.new("RGB", (4, 4)).save(tmp_path / "img.png")
    np.savez(tmp_path / "objects.npz", meta=np.array([{"format": "x"}], dtype=object))
    np.savez(tmp_path / "other.npz", a=np.ones(3))
    np.save(tmp_path / "array.npy", np.ones(3))
    for path in (
        os.path.join(small_db, "chrome.binary"),
        tmp_path / "img.png",
        tmp_path / "objects.npz",
        tmp_path / "other.npz",
        tmp_path / "array.npy",
        tmp_path,
    ):
        with pytest.raises(InputError) as e:
            Manifold.load(path)
        text = str(e.value)
        assert text.startswith(f"{path} is not a manifold .npz written by fit_manifold (")
        assert "pickle" not in text and "allow_" not in text and "\n" not in text


def test_fit_manifold_out_must_be_an_npz_name(small_db, tmp_path):
    from guarantees_helpers import assert_one_error, run_tool

    for out, fix in [
        ("m.json", "m.npz"),
        ("m", "m.npz"),
        ("sub" + os.sep, os.path.join("sub", "manifold.npz")),
    ]:
        rc, _, err = run_tool("fit_manifold", small_db, "--out", os.path.join(tmp_path, out))
        assert_one_error(rc, err, "--out", ".npz", f"use --out {tmp_path / fix}")
    assert os.listdir(tmp_path) == []


def test_saving_never_half_writes(fitted, tmp_path):
    path = tmp_path / "m.npz"
    fitted.save(path)
    before = path.read_bytes()
    broken = Manifold.load(path)
    broken.latent = np.array([["not", "numbers"]])  # makes savez fail halfway? no: json/arrays
    broken.info = {"bad": object()}  # json cannot encode this
    with pytest.raises(TypeError):
        broken.save(path)
    assert path.read_bytes() == before
    assert sorted(os.listdir(tmp_path)) == ["m.npz"]


def test_duplicate_materials_fit_and_reproduce(tmp_path):
    folder = tmp_path / "dup"
    database.make_database(folder, (8, 8, 16), ["steel", "teflon", "gold-paint"])
    shutil.copy(folder / "steel.binary", folder / "steel-copy.binary")
    m = Manifold.fit(folder, q=2)
    assert np.all(np.isfinite(m.latent))
    for i in range(m.n):
        assert np.array_equal(m.weights(m.latent[i])[1], np.eye(m.n)[i])
    assert np.isfinite(m.condition_number())
    assert set(m.coincident()) == {"steel", "steel-copy"}  # identical tables: one latent point
    assert "2 materials share their latent point" in m.summary()


def test_stiff_hyperparameters_work_or_fail_clearly(small_db):
    for l in (1e-3, 1e3):
        m = Manifold.fit(small_db, q=2, length_scale=l)
        x = m.latent[:2].mean(0)
        b, w = m.weights(x)
        assert np.all(np.isfinite(w)) and w.sum() == pytest.approx(1.0)
    try:
        m = Manifold.fit(small_db, q=2, noise=1e-10)
    except (InputError, ArithmeticError, ValueError) as e:
        assert "noise" in str(e) or "positive definite" in str(e)
    else:
        assert np.all(np.isfinite(m.weights(m.latent.mean(0))[1]))
        assert m.condition_number() < 1e16


def test_bound_terms_of_eq7(fitted):
    t = fitted.bound_terms(fitted.latent[3])
    assert t["nearest"] == 3 and t["distance"] == 0 and t["bound"] == 0
    x = fitted.latent[3] + 0.01
    t = fitted.bound_terms(x)
    table = fitted.interpolate(x, prune=0.0)[0].reshape(-1).astype(np.float64)
    z_j = fitted.tables()[t["nearest"]].astype(np.float64)
    assert np.linalg.norm(table - z_j) <= t["bound"]
    assert t["cond_K"] == pytest.approx(np.linalg.cond(fitted.K), rel=1e-6)


def test_negative_fraction_counts_what_the_plugin_clamps(fitted, small_db):
    assert fitted.negative_fraction(fitted.latent[0]) == 0.0
    assert fitted.negative_fraction(fitted.latent.mean(0) + 1e6) == 0.0
    tables = Database(small_db, fitted.names).stack().astype(np.float64)
    rng = np.random.default_rng(3)
    seen = []
    for x in fitted.latent.mean(0) + rng.normal(scale=1.0, size=(8, fitted.q)):
        expected = float(((fitted.weights(x)[1] @ tables) < 0).mean())
        assert fitted.negative_fraction(x, prune=0.0) == pytest.approx(expected, abs=1e-4)
        seen.append(expected)
    assert max(seen) > 0.01  # the random points include genuinely negative blends


def test_unknown_material_suggests_the_closest_names(small_manifold):
    from mitsuba_manifold.errors import InputError

    m = Manifold.load(small_manifold)
    with pytest.raises(InputError, match=r"unknown material 'stel' \(did you mean 'steel'"):
        m.index("stel")


def test_the_fit_is_kept_as_a_typed_record_written_in_the_info_layout(fitted, tmp_path):
    from mitsuba_manifold.manifold.file.fit_record import FitRecord

    rec = fitted.record
    assert (rec.method, rec.preset, rec.q, rec.d) == ("hooke-jeeves", "paper", 2, 3 * 32 * 32 * 64)
    assert (
        rec.dims == fitted.dims == (32, 32, 64) and rec.timings.fit_s > 0 and rec.n_evaluations > 0
    )
    assert np.array_equal(rec.history, fitted.history) and rec.log_likelihood == pytest.approx(
        fitted.history[-1], rel=1e-9
    )
    assert list(fitted.info) == list(FitRecord.INFO) and fitted.info["dims"] == [32, 32, 64]
    info = {**fitted.info, "subset_of": "elsewhere.npz"}  # an entry of another version: kept
    again = FitRecord.from_info(info, rec.history)
    assert again.extra == {"subset_of": "elsewhere.npz"} and again.as_info() == info
    m = Manifold.load(fitted.file)
    m.info = info
    assert m.record.method == "hooke-jeeves" and np.array_equal(m.history, fitted.history)
    m.save(tmp_path / "m.npz")
    assert Manifold.load(tmp_path / "m.npz").info == info


def test_the_constructor_takes_the_learned_state_as_keywords(fitted):
    m = Manifold(
        fitted.names,
        fitted.latent,
        fitted.database,
        fitted.hashes,
        fitted.length_scale,
        fitted.noise,
        fitted.features,
        fitted.albedos,
        gram=fitted.gram,
        record=fitted.record,
        interpolant=fitted.interpolant.params(),
        table_gram=fitted.table_gram,
    )
    assert (
        m.info == fitted.info and np.array_equal(m.gram, fitted.gram) and m.kernel == fitted.kernel
    )
    assert m.log_likelihood() == fitted.log_likelihood()
    bare = Manifold(fitted.names, fitted.latent, "db", fitted.hashes)
    assert bare.info == {} and bare.history.size == 0 and bare.interpolant.kind == "gp"
    args = (fitted.names, fitted.latent, "db", fitted.hashes, 1.0, 1e-4, "raw", None)
    for call in (lambda: Manifold(*args, fitted.gram), lambda: Manifold(*args, tables=None)):
        with pytest.raises(TypeError):
            call()


def test_a_manifold_and_its_tables_go_with_its_last_reference(small_manifold):
    # The continuation beyond the data reads the manifold's tables; a manifold must still be freed
    # (with the tables it holds in memory) as soon as it is unused, not at a later garbage collection.
    m = Manifold.load(small_manifold)
    assert m.interpolant.limit is not None  # the default preset continues beyond the data
    loaded = weakref.ref(m.tables())
    far = m.latent.mean(0) + 10 * (m.latent.max(0) - m.latent.min(0))
    m.weights(far)  # the continuation's limit, reading the tables
    m.path(m.names[0], m.names[1], steps=5)  # the path metric it keeps for the manifold
    gc.disable()
    try:
        del m
        assert loaded() is None
    finally:
        gc.enable()
    # an interpolant kept without its manifold says so when its limit needs the tables
    interpolant = Manifold.load(small_manifold).interpolant
    with pytest.raises(UnavailableError, match="no longer exists"):
        interpolant.b_and_w(far[None])


def test_a_stress_term_is_fitted_to_the_perceptual_distances_and_saved_with_the_fit(
    small_db, tmp_path
):
    from mitsuba_manifold.data.distance import distance_matrix
    from mitsuba_manifold.gp.stress import Stress

    plain = Manifold.fit(small_db, stress=0.0)
    assert not any(k.startswith("stress") for k in plain.info)  # off: no stress in the info
    m = Manifold.fit(small_db, stress=3.0, stress_neighbours=4)
    D = distance_matrix(m.tables(), dims=m.dims)
    sigma = Stress(1.0, 4).term(D, m.n, 1).value
    assert m.info["stress"] == 3.0 and m.info["stress_neighbours"] == 4
    assert f"stress term: weight 3, normalised stress {m.info['stress_value']:.3g}" in m.summary()
    assert "stress term" not in plain.summary()
    assert m.info["stress_value"] == pytest.approx(sigma(m.latent), rel=1e-9)
    assert sigma(m.latent) < sigma(plain.latent)
    m.save(tmp_path / "m.npz")
    assert Manifold.load(tmp_path / "m.npz").info == m.info
    with pytest.raises(InputError, match="needs method 'newton' or 'lbfgs'"):
        Manifold.fit(small_db, stress=1.0, method="hooke-jeeves")


def test_a_subset_of_a_manifold_fitted_with_stress_is_fitted_with_it(small_db):
    from mitsuba_manifold.data.distance import distance_matrix
    from mitsuba_manifold.gp.stress import Stress

    m = Manifold.fit(small_db, stress=3.0)
    names = m.names[:6]
    sub = m.subset(names)
    D = distance_matrix(sub.tables(), dims=sub.dims)
    sigma = Stress(1.0).term(D, sub.n, 1).value(sub.latent)
    assert sub.info["stress"] == 3.0 and sub.info["stress_value"] == pytest.approx(sigma, rel=1e-9)
    plain = Manifold.fit(small_db, names=names, stress=0.0)
    assert sigma < Stress(1.0).term(D, sub.n, 1).value(plain.latent)
