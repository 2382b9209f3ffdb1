"""Tests of the ``manifold_brdf`` Mitsuba BSDF (evaluation, sampling, parameters, errors).

Sampling is checked with Mitsuba's chi-square test (``mitsuba.chi2``): on the sphere for
the broad materials, and for every material on the domain of the half vector between
``wi`` and ``wo`` (``(phi_h - phi_i, u = sqrt(theta_h / (pi/2)))``), which resolves the
narrow peaks of chrome and steel that a 101x50 grid on the sphere cannot integrate.
Tables come from the shared reduced-resolution fixtures of ``conftest.py``.
"""

import os
import shutil
import subprocess
import sys

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np
import pytest
from helpers import chain  # noqa: E402
from mitsuba.chi2 import BSDFAdapter, ChiSquareTest, SphericalDomain  # noqa: E402

import mitsuba_manifold.render  # noqa: F401  (selects a working libLLVM before drjit loads; the plugins)
from mitsuba_manifold.data import merl  # noqa: E402
from mitsuba_manifold.data.database import Database  # noqa: E402
from mitsuba_manifold.manifold.model import Manifold  # noqa: E402
from mitsuba_manifold.render import integrators
from mitsuba_manifold.render.plugin import lookups, sampling  # noqa: E402
from mitsuba_manifold.render.scene.scenes import SCENES_DIR  # noqa: E402

pytestmark = [pytest.mark.render, pytest.mark.usefixtures("variant")]

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ANGLES = (0, 30, 60, 80)
CHI2_TESTS = 40  # chi-square tests in this file, for the Sidak-corrected significance level


@pytest.fixture(scope="module")
def manifold(small_manifold_paper):
    return Manifold.load(small_manifold_paper)


@pytest.fixture(scope="module")
def negative_x(manifold):
    """A latent point between materials whose weights include clearly negative values."""
    lat = manifold.latent
    best = None
    for i in range(len(lat)):
        for j in range(i + 1, len(lat)):
            x = 0.5 * (lat[i] + lat[j])
            _, w = manifold.weights(x)
            if (
                w.min() < -0.05
                and np.abs(w).sum() < 4
                and (best is None or w.min() < best[1].min())
            ):
                best = (x, w)
    assert best is not None, "no latent point with negative weights in the test manifold"
    return best[0]


@pytest.fixture(scope="module")
def random_manifold(tmp_path_factory):
    """A manifold of three random tables (8x6x12 bins): no symmetry the lookup could hide behind."""
    folder = tmp_path_factory.mktemp("random_db")
    rng = np.random.default_rng(13)
    for name in ("a", "b", "c"):
        merl.write_binary(folder / f"{name}.binary", rng.uniform(100, 2000, (3, 8, 6, 12)))
    path = str(folder / "manifold.npz")
    Manifold.fit(str(folder), q=1).save(path)
    return path


def make(path, **params):
    return mi.load_dict({"type": "manifold_brdf", "manifold": path, **params})


def incident(angle_deg, azimuth=0.0):
    a = np.radians(angle_deg)
    return [
        float(np.sin(a) * np.cos(azimuth)),
        float(np.sin(a) * np.sin(azimuth)),
        float(np.cos(a)),
    ]


def interaction(wi, n):
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = vec(wi) if np.ndim(wi) == 2 else mi.Vector3f(*wi)
    return si


def vec(a):
    return mi.Vector3f(np.ascontiguousarray(np.asarray(a, dtype=np.float32).T))


def random_directions(n, seed):
    """Uniform directions on the upper hemisphere, float32-exact, shape (n, 3)."""
    rng = np.random.default_rng(seed)
    z = rng.uniform(0.02, 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    r = np.sqrt(1 - z * z)
    d = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1).astype(np.float32)
    return d


# ------------------------------------------------------------------ chi-square


class HalfVectorDomain:
    """Chi-square domain ``(phi_h - phi_i, sqrt(theta_h / (pi/2)))`` of the half vector.

    ``map_forward`` returns the parameters themselves: the pdf functor below maps them
    to ``wo`` and multiplies the solid-angle pdf by the Jacobian ``|d wo / d(phi, u)|``.
    """

    def __init__(self, wi):
        self.wi = mi.Vector3f(*wi)
        r = float(np.hypot(wi[0], wi[1]))
        self.e = (wi[0] / r, wi[1] / r) if r > 0 else (1.0, 0.0)

    def bounds(self):
        return mi.ScalarBoundingBox2f([-dr.pi, 0.0], [dr.pi, 1.0])

    def aspect(self):
        return 1.0

    def map_forward(self, p):
        return p

    def direction(self, p):
        theta_h = dr.square(p.y) * (dr.pi / 2)
        st, ct = dr.sincos(theta_h)
        sp, cp = dr.sincos(p.x)
        ex, ey = self.e
        h = mi.Vector3f(st * (ex * cp - ey * sp), st * (ey * cp + ex * sp), ct)
        return mi.reflect(self.wi, h)

    def map_backward(self, wo):
        h = dr.normalize(self.wi + wo)
        ex, ey = self.e
        u = dr.sqrt(dr.atan2(dr.norm(mi.Vector2f(h.x, h.y)), h.z) / (dr.pi / 2))
        return mi.Vector2f(dr.atan2(ex * h.y - ey * h.x, ex * h.x + ey * h.y), dr.clip(u, 0.0, 1.0))

    def jacobian(self, wo):
        """Solid angle of ``wo`` per unit ``(phi, u)`` (taken at ``wo`` as computed)."""
        h = dr.normalize(self.wi + wo)
        sin_h = dr.norm(mi.Vector2f(h.x, h.y))
        u = dr.sqrt(dr.atan2(sin_h, h.z) / (dr.pi / 2))
        return 4.0 * dr.abs(dr.dot(self.wi, h)) * sin_h * dr.pi * u


@pytest.fixture(autouse=True)
def _debug_files_in_tmp(tmp_path, monkeypatch):
    """mitsuba.chi2 writes its debug file (chi2_data.py) into the working directory: keep it in tmp_path."""
    monkeypatch.chdir(tmp_path)


def chi2(params, angle, domain="half", ires=4):
    wi = incident(angle, azimuth=0.3 * angle)  # out of the xz plane too
    sample, pdf = BSDFAdapter("manifold_brdf", {"type": "manifold_brdf", **params}, wi=wi)
    if domain == "half":
        dom = HalfVectorDomain(wi)

        def pdf_func(p):
            wo = dom.direction(p)
            return pdf(wo) * dom.jacobian(wo)

        test = ChiSquareTest(dom, sample, pdf_func, sample_dim=3, res=101, ires=ires)
    else:
        test = ChiSquareTest(SphericalDomain(), sample, pdf, sample_dim=3, res=101, ires=ires)
    ok = test.run(0.01, test_count=CHI2_TESTS, quiet=True)
    return ok, f"{params} at {angle} deg ({domain}): p = {test.p_value}\n{test.messages}"


@pytest.mark.parametrize(
    "material",
    ["pink-fabric", "gold-paint", "chrome", "steel", "color-changing-paint3", "interpolated"],
)
def test_chi2_half_vector_domain(small_manifold_paper, negative_x, material):
    if material == "interpolated":
        params = {
            "manifold": small_manifold_paper,
            "x": ", ".join(repr(float(v)) for v in negative_x),
        }
    else:
        params = {"manifold": small_manifold_paper, "material": material}
    for angle in ANGLES:
        ok, report = chi2(params, angle)
        assert ok, report


@pytest.mark.parametrize("material", ["pink-fabric", "white-diffuse-bball", "gold-paint"])
def test_chi2_sphere_domain(small_manifold_paper, material):
    params = {"manifold": small_manifold_paper, "material": material}
    for angle in ANGLES:
        ok, report = chi2(params, angle, domain="sphere", ires=8)
        assert ok, report


@pytest.mark.parametrize(
    "params",
    [
        {"material": "chrome", "interpolation": "linear"},
        {"material": "steel", "sampling": "cosine"},
    ],
)
def test_chi2_options(small_manifold_paper, params):
    ok, report = chi2({"manifold": small_manifold_paper, **params}, 60)
    assert ok, report


def test_chi2_at_89_degrees(small_manifold_paper):
    # Near grazing incidence MERL zeroes bins whose centre is below the horizon: the
    # density has many small discontinuities, hence the finer integration of the pdf.
    ok, report = chi2({"manifold": small_manifold_paper, "material": "chrome"}, 89, ires=16)
    assert ok, report


# ------------------------------------------------------------------ evaluation


def test_lookup_agrees_with_merl_indexing():
    dims = (90, 90, 180)
    wi, wo = random_directions(200_000, 1), random_directions(200_000, 2)
    wi64, wo64 = wi.astype(np.float64), wo.astype(np.float64)
    expected = merl.flat_index(wi64, wo64, dims)
    got = np.array(lookups.merl_bin(*lookups.merl_angles(vec(wi), vec(wo)), dims))
    # Distance to the nearest bin boundary (in bins): float32 may round across it.
    th, td, pd = merl.half_diff(wi64, wo64)
    c = [
        np.sqrt(th / (np.pi / 2)) * dims[0],
        td / (np.pi / 2) * dims[1],
        np.mod(pd, np.pi) / np.pi * dims[2],
    ]
    margin = np.min([np.abs(x - np.round(x)) for x in c], axis=0)
    clear = margin > 1e-3
    assert clear.mean() > 0.99
    assert np.array_equal(got[clear], expected[clear])
    assert (got != expected).mean() < 1e-3


def test_training_material_evaluates_to_its_table(small_manifold_paper, small_db):
    db = Database(small_db)
    table = np.asarray(db.reflectance("chrome"))
    bsdf = make(small_manifold_paper, material="chrome")
    assert bsdf.weights.tolist() == [1.0 if n == "chrome" else 0.0 for n in bsdf.names]
    dims = table.shape[1:]
    th, td, pd = merl.bin_centres(dims)
    rng = np.random.default_rng(3)
    phi_h = rng.uniform(0, 2 * np.pi, dims)
    wi, wo = merl.directions(th, td, pd, phi_h)
    wi, wo = wi.reshape(-1, 3).astype(np.float32), wo.reshape(-1, 3).astype(np.float32)
    keep = (wi[:, 2] > 1e-3) & (wo[:, 2] > 1e-3) & merl.above_horizon(dims).ravel()
    idx = np.flatnonzero(keep)
    value = np.array(bsdf.eval(mi.BSDFContext(), interaction(wi[idx], len(idx)), vec(wo[idx])))
    expected = table.reshape(3, -1)[:, idx] * wo[idx, 2][None, :]
    assert keep.sum() > 0.6 * np.prod(dims)
    assert np.array_equal(value, expected.astype(np.float32))


def test_eval_is_reciprocal_and_one_sided(small_manifold_paper, negative_x):
    x = ", ".join(repr(float(v)) for v in negative_x)
    wi, wo = random_directions(100_000, 4), random_directions(100_000, 5)
    ctx = mi.BSDFContext()
    for interpolation in ("nearest", "linear"):
        bsdf = make(small_manifold_paper, x=x, interpolation=interpolation)
        f_io = np.array(bsdf.eval(ctx, interaction(wi, len(wi)), vec(wo))) / wo[:, 2]
        f_oi = np.array(bsdf.eval(ctx, interaction(wo, len(wo)), vec(wi))) / wi[:, 2]
        close = np.isclose(f_io, f_oi, rtol=1e-3, atol=1e-6).all(axis=0)
        assert close.mean() > 0.999, interpolation
        assert (f_io > 0).any(axis=0).mean() > 0.5
    below = wo * np.array([1, 1, -1], dtype=np.float32)
    si = interaction(wi, len(wi))
    assert dr.all(bsdf.eval(ctx, si, vec(below)) == 0, axis=None)
    assert dr.all(bsdf.pdf(ctx, si, vec(below)) == 0)
    si_below = interaction(below, len(below))
    assert dr.all(bsdf.eval(ctx, si_below, vec(wo)) == 0, axis=None)
    bs, weight = bsdf.sample(ctx, si_below, mi.Float(0.5), mi.Point2f(0.3, 0.6))
    assert dr.all(weight == 0, axis=None) and dr.all(bs.pdf == 0)


def test_linear_interpolation_is_periodic_in_phi_d(random_manifold):
    m = Manifold.load(random_manifold)
    table = np.asarray(m.open_database().reflectance("b"))
    n_h, n_d, n_p = table.shape[1:]
    bsdf = make(random_manifold, material="b", interpolation="linear")
    i_h, i_d = 2, 1
    th = ((i_h + 0.5) / n_h) ** 2 * np.pi / 2
    td = (i_d + 0.5) / n_d * np.pi / 2
    # A quarter bin on either side of phi_d = 0 (= pi): the first and last bins mix.
    first, last = table[:, i_h, i_d, 0], table[:, i_h, i_d, n_p - 1]
    pd = np.array([0.25 / n_p * np.pi, np.pi - 0.25 / n_p * np.pi, 4.0 / n_p * np.pi])
    expected = np.stack(
        [
            0.75 * first + 0.25 * last,
            0.25 * first + 0.75 * last,
            0.5 * (table[:, i_h, i_d, 3] + table[:, i_h, i_d, 4]),
        ],
        axis=1,
    )
    wi, wo = merl.directions(np.full(3, th), np.full(3, td), pd, phi_h=1.0)
    value = np.array(
        bsdf.eval(
            mi.BSDFContext(), interaction(wi.astype(np.float32), 3), vec(wo.astype(np.float32))
        )
    ) / wo[:, 2].astype(np.float32)
    assert not np.allclose(first, last, rtol=1e-2)
    assert np.allclose(value, expected, rtol=2e-3)
    nearest = make(random_manifold, material="b")
    value = np.array(
        nearest.eval(
            mi.BSDFContext(), interaction(wi.astype(np.float32), 3), vec(wo.astype(np.float32))
        )
    ) / wo[:, 2].astype(np.float32)
    assert np.allclose(value[:, :2], table[:, i_h, i_d, [0, n_p - 1]], rtol=1e-6)


def albedo_quadrature(table, wi, n_u=1024, n_phi=512):
    """Directional albedo of a table by the midpoint rule over the half vector (NumPy)."""
    u = (np.arange(n_u) + 0.5) / n_u
    phi = (np.arange(n_phi) + 0.5) / n_phi * 2 * np.pi
    U, PHI = np.meshgrid(u, phi, indexing="ij")
    th = U * U * np.pi / 2
    h = np.stack([np.sin(th) * np.cos(PHI), np.sin(th) * np.sin(PHI), np.cos(th)], -1)
    wi = np.broadcast_to(np.asarray(wi, dtype=np.float64), h.shape)
    cos_d = np.sum(wi * h, -1)
    wo = 2 * cos_d[..., None] * h - wi
    ok = (wo[..., 2] > 0) & (cos_d > 0)
    f = table.reshape(3, -1)[:, merl.flat_index(wi[ok], wo[ok], table.shape[1:])]
    jac = 4 * cos_d[ok] * np.sin(th[ok]) * np.pi * U[ok]
    return (f * wo[ok][:, 2] * jac).sum(axis=1) / n_u * (2 * np.pi / n_phi)


@pytest.mark.parametrize("spec", ["chrome", "interpolated"])
def test_white_furnace(small_manifold_paper, manifold, negative_x, spec):
    if spec == "interpolated":
        bsdf = make(small_manifold_paper, x=", ".join(repr(float(v)) for v in negative_x))
    else:
        bsdf = make(small_manifold_paper, material=spec)
    table = np.maximum(manifold.combine(bsdf.weights)[0], 0.0)
    n = 1 << 20
    rng = np.random.default_rng(6)
    s = rng.random((3, n)).astype(np.float32)
    for angle in (30, 80):
        wi = incident(angle)
        _, weight = bsdf.sample(
            mi.BSDFContext(), interaction(wi, n), mi.Float(s[0]), mi.Point2f(s[1], s[2])
        )
        weight = np.array(weight)
        mean, err = weight.mean(axis=1), weight.std(axis=1) / np.sqrt(n)
        expected = albedo_quadrature(table, wi)
        assert expected.min() > 0.01
        assert np.all(np.abs(mean - expected) < 5 * err + 1e-3 * expected), (
            angle,
            mean,
            expected,
            err,
        )


def test_sampling_concentrates_on_spiky_materials(small_manifold_paper):
    """Tabulated sampling estimates chrome's albedo with far less noise than cosine sampling."""
    n = 1 << 18
    s = np.random.default_rng(7).random((3, n)).astype(np.float32)
    errors = {}
    for mode in ("cdf", "cosine"):
        bsdf = make(small_manifold_paper, material="chrome", sampling=mode)
        _, weight = bsdf.sample(
            mi.BSDFContext(), interaction(incident(45), n), mi.Float(s[0]), mi.Point2f(s[1], s[2])
        )
        w = np.array(weight).mean(axis=0)
        errors[mode] = w.std() / w.mean()
    assert errors["cdf"] * 5 < errors["cosine"]


def test_no_fireflies_at_the_mirror_direction(small_manifold_paper):
    """Samples that single precision rounds onto the mirror direction keep small weights."""
    bsdf = make(small_manifold_paper, material="chrome")
    rng = np.random.default_rng(11)
    n = 4096
    wi = random_directions(n, 12)
    sx = rng.choice(np.array([0.0, 1e-9, 1e-7, 1e-6, 1e-5], dtype=np.float32), n)
    s1 = rng.uniform(0.2, 1.0, n).astype(np.float32)  # the tabulated strategy
    _, weight = bsdf.sample(
        mi.BSDFContext(),
        interaction(wi, n),
        mi.Float(s1),
        mi.Point2f(mi.Float(sx), mi.Float(rng.random(n).astype(np.float32))),
    )
    weight = np.array(weight)
    assert np.isfinite(weight).all() and weight.max() < 1.0


# ------------------------------------------------------------------ parameters


def test_traverse_x_rebuilds(small_manifold_paper, manifold, negative_x):
    bsdf = make(small_manifold_paper, x="0.1, 0.2")
    params = mi.traverse(bsdf)
    assert "x" in params
    assert np.allclose(bsdf.weights, manifold.weights([0.1, 0.2])[1])
    si = interaction(incident(40), 1)
    wo = mi.Vector3f(*incident(-35))
    before = np.array(bsdf.eval(mi.BSDFContext(), si, wo))
    params["x"] = mi.Float(negative_x)
    params.update()
    assert np.allclose(bsdf.latent, negative_x.astype(np.float32))
    assert np.allclose(bsdf.weights, manifold.weights(np.array(params["x"], dtype=np.float64))[1])
    after = np.array(bsdf.eval(mi.BSDFContext(), si, wo))
    assert not np.allclose(before, after)
    bsdf.set_material("chrome")  # the parameters object keeps driving the same material
    assert np.allclose(np.array(params["x"]), manifold.latent[manifold.index("chrome")])
    params["x"] = mi.Float([0.1, 0.2])
    params.update()
    assert np.allclose(bsdf.weights, manifold.weights(np.array([0.1, 0.2], dtype=np.float32))[1])
    assert np.allclose(np.array(bsdf.eval(mi.BSDFContext(), si, wo)), before, rtol=1e-5)


def test_python_methods_switch_materials(small_manifold_paper, small_db, manifold):
    bsdf = make(small_manifold_paper, x="0, 0")
    from mitsuba_manifold.render.plugin import bsdf as manifold_brdf

    assert isinstance(bsdf, manifold_brdf.ManifoldBRDF) and isinstance(bsdf, mi.BSDF)
    assert bsdf.names == manifold.names and isinstance(bsdf.manifold, Manifold)
    ctx, si = mi.BSDFContext(), interaction(incident(30), 1)
    wo = mi.Vector3f(*incident(-31))
    bsdf.set_material("steel")
    steel = np.asarray(Database(small_db).reflectance("steel"))
    f = np.array(bsdf.eval(ctx, si, wo))[:, 0] / np.float32(wo.z[0])
    idx = merl.flat_index(np.array(incident(30)), np.array(incident(-31)), steel.shape[1:])
    assert np.allclose(f, steel.reshape(3, -1)[:, idx], rtol=1e-6)
    assert bsdf.used_names == ["steel"] and np.allclose(
        bsdf.latent, manifold.latent[manifold.index("steel")]
    )
    bsdf.set_weights({"steel": 0.5, "chrome": 0.5})
    assert bsdf.latent is None and sorted(bsdf.used_names) == ["chrome", "steel"]
    w = np.zeros(len(manifold.names))
    w[manifold.index("pink-fabric")] = 1.0
    bsdf.set_weights(w)
    assert bsdf.used_names == ["pink-fabric"]
    bsdf.set_latent([0.3, -0.2])
    assert np.allclose(bsdf.weights, manifold.weights([0.3, -0.2])[1])
    with pytest.raises(ValueError, match="latent dimension"):
        bsdf.set_latent([1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="sum to zero"):
        bsdf.set_weights({"steel": 1.0, "chrome": -1.0})
    assert np.allclose(
        bsdf.weights, manifold.weights([0.3, -0.2])[1]
    )  # failed calls change nothing


def test_clamping_and_pruning_are_reported(small_manifold_paper, manifold, negative_x):
    x = ", ".join(repr(float(v)) for v in negative_x)
    bsdf = make(small_manifold_paper, x=x, prune=0.0)
    table = manifold.combine(manifold.weights(negative_x)[1], prune=0.0)[0]
    assert bsdf.clamped_bins == int((table < 0).sum()) > 0
    assert f"clamped bins = {bsdf.clamped_bins} of" in str(bsdf)
    # pruning: at a point near two materials most weights are small
    near = 0.8 * manifold.latent[0] + 0.2 * manifold.latent[1]
    w = manifold.weights(near).w
    pruned = make(small_manifold_paper, x=", ".join(repr(float(v)) for v in near), prune=0.05)
    keep, _, dropped = manifold.prune(w, 0.05)
    assert pruned.used_names == [manifold.names[i] for i in keep] and len(keep) < len(
        manifold.names
    )
    assert pruned.dropped_weight == pytest.approx(dropped) and dropped > 0
    assert f"dropped weight {dropped:.4g}" in str(pruned)
    assert (
        pruned.prune_error == pytest.approx(manifold.prune_error(w, keep))
        and pruned.prune_error <= 0.05
    )
    text = str(pruned)
    assert (
        f"pruning: {len(keep)} of " in text
        and "albedo change" in text
        and "cosine-weighted table error" in text
    )


def test_sampling_cache(small_manifold_paper, small_db, tmp_path):
    folder = tmp_path / "db"
    shutil.copytree(small_db, folder, ignore=shutil.ignore_patterns(".manifold-cache"))
    db = Database(folder)
    path = sampling.sampling_cache_path(db, "chrome")
    assert not os.path.exists(path)
    make(small_manifold_paper, material="chrome", database=str(folder))
    assert os.path.dirname(path) == db.cache_dir and db.hash("chrome") in os.path.basename(path)
    cached = np.load(path)
    assert np.array_equal(cached, sampling.sampling_density(db.reflectance("chrome")))
    with open(path, "wb") as f:
        f.write(b"garbage")
    make(small_manifold_paper, material="chrome", database=str(folder))
    assert np.array_equal(np.load(path), cached)


def test_relative_paths_resolve_against_the_scene(small_manifold_paper, small_db, tmp_path):
    shutil.copy(small_manifold_paper, tmp_path / "m.npz")
    shutil.copytree(small_db, tmp_path / "tables")
    (tmp_path / "s.xml").write_text(
        '<scene version="3.0.0"><shape type="sphere"><bsdf type="manifold_brdf">'
        '<string name="manifold" value="m.npz"/><string name="database" value="tables"/>'
        '<string name="material" value="gold-paint"/></bsdf></shape></scene>'
    )
    cwd = os.getcwd()
    os.chdir(ROOT)
    try:
        scene = mi.load_file(str(tmp_path / "s.xml"))
    finally:
        os.chdir(cwd)
    bsdf = scene.shapes()[0].bsdf()
    assert integrators.is_manifold_bsdf(bsdf) and bsdf.used_names == ["gold-paint"]
    assert str(tmp_path / "tables") in str(bsdf)


def test_printed_material_pastes_into_a_scene(small_manifold_paper, manifold):
    """``print(bsdf)``'s material line is the parameter as a scene gives it: pasted into an XML
    scene it gives back the same latent point, to the last bit, and the same material.
    """

    def pasted(bsdf, key):
        lines = [ln.strip().rstrip(",") for ln in str(bsdf).splitlines()]
        chosen = [ln for ln in lines if ln.startswith(key + " = ")]
        assert len(chosen) == 1, str(bsdf)
        name, _, value = chosen[0].partition(" = ")
        scene = mi.load_string(
            '<scene version="3.0.0"><shape type="sphere"><bsdf type="manifold_brdf">'
            f'<string name="manifold" value="{small_manifold_paper}"/>'
            f'<string name="{name}" value={value}/></bsdf></shape></scene>'
        )
        return scene.shapes()[0].bsdf()

    x = 0.37 * manifold.latent[0] + 0.63 * manifold.latent[1] + 1e-7 / 3
    bsdf = make(small_manifold_paper, x=", ".join(repr(float(v)) for v in x))
    again = pasted(bsdf, "x")
    assert np.array_equal(again.latent, x) and np.array_equal(again.weights, bsdf.weights)
    assert pasted(make(small_manifold_paper, material="chrome"), "material").used_names == [
        "chrome"
    ]


@pytest.mark.parametrize(
    "params, message",
    [
        ({"material": "unobtainium"}, "unknown material 'unobtainium'"),
        ({"x": "0.1, 0.2, 0.3"}, "latent dimension"),
        ({"x": "0.1, nope"}, "'nope' is not a number"),
        ({"weights": "chrome:1, steel:-1"}, "sum to zero"),
        ({"weights": "chrome:1, gold:0.5"}, "unknown material 'gold'"),
        ({}, "exactly one of 'x', 'material' and 'weights'"),
        ({"x": "0, 0", "material": "chrome"}, "exactly one of"),
        ({"material": "chrome", "sampling": "magic"}, "sampling must be one of"),
        ({"material": "chrome", "interpolation": "cubic"}, "interpolation must be one of"),
        ({"material": "chrome", "prune": 1.5}, "prune must be in"),
        (
            {"material": "chrome", "database": "/nonexistent/tables"},
            "database folder '/nonexistent/tables' not found",
        ),
    ],
)
def test_bad_parameters(small_manifold_paper, params, message):
    with pytest.raises(Exception) as info:
        make(small_manifold_paper, **params)
    assert message in chain(info.value)


def test_missing_manifold_or_database(small_manifold_paper, tmp_path):
    with pytest.raises(Exception) as info:
        mi.load_dict({"type": "manifold_brdf", "material": "chrome"})
    assert "'manifold' parameter" in chain(info.value)
    with pytest.raises(Exception) as info:
        make(str(tmp_path / "missing.npz"), material="chrome")
    assert "manifold file '" + str(tmp_path / "missing.npz") + "' not found" in chain(info.value)
    with pytest.raises(Exception) as info:  # a database without a shipped manifold: how to make one
        make("sgd", material="chrome")
    assert "fit_manifold.py sgd --out sgd.npz" in chain(info.value)
    assert "name a shipped manifold (merl, rgl, nielsen, all)" in chain(info.value)
    assert make("merl", material="chrome").manifold.n == 100  # the shipped default
    moved = Manifold.load(small_manifold_paper)
    moved.database = str(tmp_path / "moved-away")
    moved.save(tmp_path / "moved.npz")
    with pytest.raises(Exception) as info:
        make(str(tmp_path / "moved.npz"), material="chrome")
    assert str(tmp_path / "moved-away") in chain(info.value) and "does not exist" in chain(
        info.value
    )


def test_database_must_match_the_manifold(small_manifold_paper, small_db, tmp_path):
    folder = tmp_path / "other"
    shutil.copytree(small_db, folder, ignore=shutil.ignore_patterns(".manifold-cache"))
    raw = merl.read_binary(folder / "steel.binary")
    merl.write_binary(folder / "steel.binary", np.where(raw >= 0, raw * 1.01, raw))
    make(small_manifold_paper, material="chrome", database=str(folder))  # other tables are not read
    with pytest.raises(Exception) as info:
        make(small_manifold_paper, material="steel", database=str(folder))
    assert "'steel' differs from the one the manifold was fit on" in chain(info.value)
    os.remove(folder / "chrome.binary")
    with pytest.raises(Exception) as info:
        make(small_manifold_paper, material="chrome", database=str(folder))
    assert "chrome" in chain(info.value) and str(folder) in chain(info.value)


# ------------------------------------------------------------------ variants and scenes


def test_scalar_variant_matches_llvm(small_manifold_paper, negative_x):
    x = ", ".join(repr(float(v)) for v in negative_x)
    wi, wo = random_directions(6, 8), random_directions(6, 9)
    samples = np.random.default_rng(10).random((6, 3))
    results = {}
    for variant in ("llvm_ad_rgb", "scalar_rgb"):
        mi.set_variant(variant)  # the plugins follow (mitsuba_manifold.render.plugin.plugins)
        ctx = mi.BSDFContext()
        out = []
        for interpolation in ("nearest", "linear"):
            bsdf = make(small_manifold_paper, x=x, interpolation=interpolation)
            for k in range(len(wi)):
                si = dr.zeros(mi.SurfaceInteraction3f)
                si.wi = mi.Vector3f(*map(float, wi[k]))
                d = mi.Vector3f(*map(float, wo[k]))
                f, p = bsdf.eval_pdf(ctx, si, d)
                bs, weight = bsdf.sample(
                    ctx, si, float(samples[k, 0]), mi.Point2f(*map(float, samples[k, 1:]))
                )
                out.append(
                    np.concatenate(
                        [
                            np.ravel(f),
                            np.ravel(p),
                            np.ravel(bs.wo),
                            np.ravel(weight),
                            np.ravel(bs.pdf),
                        ]
                    ).astype(np.float64)
                )
        results[variant] = np.array(out)
    assert np.allclose(results["scalar_rgb"], results["llvm_ad_rgb"], rtol=1e-4, atol=1e-6)
    assert (results["llvm_ad_rgb"][:, 0] > 0).any()


def test_non_rgb_variants_are_refused_clearly(small_manifold_paper):
    mi.set_variant("scalar_spectral")
    with pytest.raises(Exception) as info:
        make(small_manifold_paper, material="chrome")
    assert "need an RGB variant" in chain(info.value)


@pytest.mark.parametrize("order", ["variant first", "import first"])
def test_import_registers_for_the_active_variant(order):
    """``import mitsuba_manifold.render`` registers the plugins, before or after ``mi.set_variant``."""
    steps = ["import mitsuba as mi; mi.set_variant('scalar_rgb')", "import mitsuba_manifold.render"]
    code = "\n".join(steps if order == "variant first" else steps[::-1]) + (
        "\ntry:\n    mi.load_dict({'type': 'manifold_brdf'})\n"
        "except Exception as e:\n    print('manifold' in str(e) and 'required' in str(e))\n"
    )
    env = dict(os.environ, PYTHONPATH=ROOT + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, env=env
    )
    assert out.stdout.strip() == "True", out.stderr


def test_sphere_scene_renders(small_manifold_paper, negative_x, tmp_path):
    """scenes/sphere.xml renders an interpolated material; both sampling strategies agree."""
    from mitsuba_manifold.render.plugin import (
        bsdf as manifold_brdf,
    )  # the class of the active variant

    for name in ("sphere.xml", "sky.exr"):
        shutil.copy(os.path.join(SCENES_DIR, name), tmp_path / name)
    text = (tmp_path / "sphere.xml").read_text()
    line = '<string name="x" value="$x"/>'
    assert line in text
    (tmp_path / "cosine.xml").write_text(
        text.replace(line, line + '<string name="sampling" value="cosine"/>')
    )
    x = ", ".join(repr(float(v)) for v in negative_x)
    means = {}
    for name, spp in (("sphere.xml", 64), ("cosine.xml", 512)):
        scene = mi.load_file(
            str(tmp_path / name), manifold=small_manifold_paper, x=x, res=24, spp=spp
        )
        (bsdf,) = [
            s.bsdf() for s in scene.shapes() if isinstance(s.bsdf(), manifold_brdf.ManifoldBRDF)
        ]
        assert np.allclose(bsdf.latent, negative_x.astype(np.float32))
        img = np.array(mi.render(scene))
        assert np.isfinite(img).all() and img.min() >= 0 and img.mean() > 0
        means[name] = img.mean()
    assert means["sphere.xml"] == pytest.approx(means["cosine.xml"], rel=0.03)
