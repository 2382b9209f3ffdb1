"""The [PR12]-style BRDF distance: a metric, its quadrature, its layouts and sub-grids."""

import numpy as np
import pytest

from mitsuba_manifold.data import distance, merl
from mitsuba_manifold.data.database import Database
from mitsuba_manifold.errors import InputError

DIMS = (8, 8, 16)


def random_tables(n, seed=0, dims=DIMS):
    """Random non-negative tables, spiky like measured ones (log-normal), 0 below the horizon."""
    rng = np.random.default_rng(seed)
    t = np.exp(rng.normal(-2.0, 1.5, size=(n, 3) + dims))
    return np.where(merl.above_horizon(dims), t, 0.0)


def test_distance_is_a_metric_on_random_tables():
    T = random_tables(12)
    D = distance.distance_matrix(T)
    assert D.shape == (12, 12)
    assert np.all(np.diag(D) == 0.0)
    assert np.allclose(D, D.T, rtol=0, atol=0)
    assert (D[~np.eye(12, dtype=bool)] > 0).all()
    # triangle inequality over every triple
    assert (D[:, None, :] <= D[:, :, None] + D[None, :, :] + 1e-12).all()
    # each entry is the exact, broadcast pairwise distance
    pair = distance.brdf_distance(T[:, None], T[None])
    assert np.allclose(D, pair, rtol=1e-9, atol=1e-12)
    assert distance.brdf_distance(T[3], T[3]) == 0.0
    assert distance.brdf_distance(T[3], T[5]) == pytest.approx(
        distance.brdf_distance(T[5], T[3]), rel=1e-14
    )


def test_two_stacks_and_the_identical_rows_in_them():
    T = random_tables(6, seed=1)
    D = distance.distance_matrix(T[:4], T[2:])
    assert D.shape == (4, 4)
    assert D[2, 0] == 0.0 and D[3, 1] == 0.0  # the same tables in both stacks: exactly 0
    assert np.allclose(D, distance.brdf_distance(T[:4, None], T[None, 2:]), rtol=1e-9)


def test_lambertian_distance_matches_the_closed_form():
    """Two Lambertian tables rho/pi: d = |cbrt(r1/pi) - cbrt(r2/pi)| sqrt(E[(cos_i cos_o)^(2/3)]),
    and over the uniform solid-angle measure E[cos^(2/3)] = 3/5 per hemisphere, so the factor is 0.6."""
    dims = (45, 45, 90)
    above = merl.above_horizon(dims)
    rho = np.array([[0.8, 0.5, 0.2], [0.1, 0.3, 0.6]])
    T = np.where(above, rho[:, :, None, None, None] / np.pi, 0.0)
    expected = 0.6 * np.sqrt(np.mean((np.cbrt(rho[0] / np.pi) - np.cbrt(rho[1] / np.pi)) ** 2))
    assert distance.brdf_distance(T[0], T[1]) == pytest.approx(expected, rel=0.01)


def test_layouts_agree_channel_first_last_and_flat():
    T = random_tables(3, seed=2)
    ref = distance.brdf_distance(T[0], T[1])
    last = np.moveaxis(T, 1, -1)
    flat = T.reshape(3, -1)
    assert distance.brdf_distance(last[0], last[1]) == pytest.approx(ref, rel=1e-12)
    assert distance.brdf_distance(flat[0], flat[1], dims=DIMS) == pytest.approx(ref, rel=1e-12)
    assert np.allclose(
        distance.distance_matrix(flat, dims=DIMS), distance.distance_matrix(T), rtol=1e-9
    )
    with pytest.raises(InputError, match="`tables`"):
        distance.brdf_distance(flat[0], flat[1])
    with pytest.raises(InputError, match="different resolutions"):
        distance.brdf_distance(T[0], random_tables(1, dims=(8, 8, 8))[0])


def test_a_sub_grid_estimates_the_full_grid(small_db):
    """The search sub-grid of the path module is within a few percent on surrogate tables."""
    db = Database(small_db)
    T = db.stack(db.names)
    full = distance.distance_matrix(T, dims=db.dims)
    coarse = distance.distance_matrix(T, dims=db.dims, stride=(1, 5, 10))
    iu = np.triu_indices(len(T), 1)
    ratio = coarse[iu] / full[iu]
    assert np.abs(ratio - 1).max() < 0.05, ratio
    quad = distance.Quadrature.of(db.dims, (1, 5, 10))
    assert quad.size < 0.1 * T.shape[1]
    # the cells' measure covers the same integral: weights sum to 1 on both grids
    assert (quad.scale**2).sum() == pytest.approx(1.0, rel=0.02)
    assert (distance.Quadrature.of(db.dims).scale ** 2).sum() == pytest.approx(1.0, rel=1e-9)
    with pytest.raises(InputError, match="`stride`"):
        distance.Quadrature.of(db.dims, (0, 1, 1))


def test_the_cube_root_compresses_highlights():
    """Doubling a spike changes d far less than L2 would: cbrt(2) - 1 of the spike's root, not 1x."""
    base = random_tables(1, seed=3)[0]
    spiky = base.copy()
    spiky[:, 0, 0, 0] += 1e3
    doubled = base.copy()
    doubled[:, 0, 0, 0] += 2e3
    d1 = distance.brdf_distance(base, spiky)
    d2 = distance.brdf_distance(base, doubled)
    assert d2 / d1 < 1.35  # plain L2: 2
