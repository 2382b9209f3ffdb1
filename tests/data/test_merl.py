"""MERL file format and half/diff mapping."""

import os

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mitsuba_manifold.data import merl

DIMS = (6, 5, 8)


def _random_raw(dims=DIMS, seed=0):
    rng = np.random.default_rng(seed)
    raw = rng.uniform(-1, 2000, (3,) + dims)
    raw[raw < 0] = -1.0
    return raw


def test_round_trip_is_bit_exact(tmp_path):
    raw = _random_raw()
    a, b = tmp_path / "a.binary", tmp_path / "b.binary"
    merl.write_binary(a, raw)
    back = merl.read_binary(a)
    assert back.shape == (3,) + DIMS
    assert np.array_equal(back, raw)
    merl.write_binary(b, back)
    assert a.read_bytes() == b.read_bytes()
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(a).st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's private 0600


def test_layout_matches_merl_reference(tmp_path):
    """Header = 3 little-endian int32, then R, G, B blocks with phi_d varying fastest."""
    n = int(np.prod(DIMS))
    values = np.arange(3 * n, dtype="<f8")
    path = tmp_path / "hand.binary"
    path.write_bytes(np.array(DIMS, dtype="<i4").tobytes() + values.tobytes())
    raw = merl.read_binary(path)
    # MERL's lookup: index = phi_d + theta_d * n_phi + theta_h * n_phi * n_d, green block at + n
    i_h, i_d, i_p = 2, 3, 5
    ind = i_p + i_d * DIMS[2] + i_h * DIMS[2] * DIMS[1]
    assert raw[0, i_h, i_d, i_p] == ind
    assert raw[1, i_h, i_d, i_p] == ind + n
    assert raw[2, i_h, i_d, i_p] == ind + 2 * n
    assert np.allclose(merl.reflectance(raw)[:, 0, 0, 0], np.array([0, n, 2 * n]) * merl.SCALE)


def test_truncated_header_mismatch_and_foreign_files(tmp_path):
    good = tmp_path / "good.binary"
    merl.write_binary(good, _random_raw())
    data = good.read_bytes()
    cases = {
        "truncated": data[:-8],
        "trailing data": data + b"\0" * 8,
        "not a MERL": b"hello, this is a text file, not a BRDF table at all" * 3,
        "header needs 12": b"abc",
    }
    for expected, content in cases.items():
        bad = tmp_path / "bad.binary"
        bad.write_bytes(content)
        with pytest.raises(merl.FormatError) as err:
            merl.read_binary(bad)
        assert str(bad) in str(err.value) and expected in str(err.value)


def test_nan_and_inf_are_rejected(tmp_path):
    raw = _random_raw()
    path = tmp_path / "x.binary"
    merl.write_binary(path, raw)
    data = bytearray(path.read_bytes())
    data[12 + 8 * 7 : 12 + 8 * 8] = np.array([np.nan]).tobytes()
    data[12 + 8 * 9 : 12 + 8 * 10] = np.array([np.inf]).tobytes()
    path.write_bytes(bytes(data))
    with pytest.raises(merl.FormatError, match="2 values are NaN or Inf"):
        merl.read_binary(path)
    with pytest.raises(ValueError, match="NaN or Inf"):
        merl.write_binary(tmp_path / "y.binary", np.full((3,) + DIMS, np.nan))


@settings(max_examples=60, deadline=None)
@given(
    cut=st.integers(min_value=0, max_value=12 + 3 * 8 * 240 - 1),
    header=st.tuples(st.integers(-5, 300), st.integers(-5, 300), st.integers(-5, 300)),
)
def test_fuzzed_corrupt_files_raise_clear_errors(tmp_path_factory, cut, header):
    folder = tmp_path_factory.mktemp("fuzz")
    raw = _random_raw()
    good = folder / "g.binary"
    merl.write_binary(good, raw)
    data = good.read_bytes()
    truncated = folder / "t.binary"
    truncated.write_bytes(data[:cut])
    with pytest.raises(merl.FormatError, match="t.binary"):
        merl.read_binary(truncated)
    if header != DIMS:
        wrong = folder / "h.binary"
        wrong.write_bytes(np.array(header, dtype="<i4").tobytes() + data[12:])
        with pytest.raises(merl.FormatError, match="h.binary"):
            merl.read_binary(wrong)


def test_failed_write_keeps_existing_file(tmp_path):
    path = tmp_path / "keep.binary"
    merl.write_binary(path, _random_raw())
    before = path.read_bytes()
    with pytest.raises(ValueError):
        merl.write_binary(path, np.zeros((2, 3)))
    with pytest.raises(ValueError):
        merl.write_binary(path, np.full((3,) + DIMS, np.inf))
    assert path.read_bytes() == before
    assert os.listdir(tmp_path) == ["keep.binary"]


def _random_pairs(n, seed=1):
    rng = np.random.default_rng(seed)
    v = rng.normal(size=(2, n, 3))
    v[..., 2] = np.abs(v[..., 2])
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    return v[0], v[1]


def test_half_diff_matches_direct_vector_computation():
    wi, wo = _random_pairs(5000)
    th, td, pd = merl.half_diff(wi, wo)
    h = (wi + wo) / np.linalg.norm(wi + wo, axis=-1, keepdims=True)
    phi_h = np.arctan2(h[:, 1], h[:, 0])
    theta_h = np.arccos(h[:, 2])
    # Frame around h: e1 = d h / d theta_h, e2 = d h / d phi_h (normalised), e3 = h.
    e1 = np.stack(
        [np.cos(theta_h) * np.cos(phi_h), np.cos(theta_h) * np.sin(phi_h), -np.sin(theta_h)], -1
    )
    e2 = np.stack([-np.sin(phi_h), np.cos(phi_h), np.zeros_like(phi_h)], -1)
    d = np.stack([(wi * e1).sum(-1), (wi * e2).sum(-1), (wi * h).sum(-1)], -1)
    assert np.allclose(th, theta_h, atol=1e-12)
    assert np.allclose(td, np.arccos(np.clip(d[:, 2], -1, 1)), atol=1e-7)
    assert np.allclose(np.exp(1j * pd), np.exp(1j * np.arctan2(d[:, 1], d[:, 0])), atol=1e-7)


def test_directions_invert_half_diff():
    rng = np.random.default_rng(2)
    th, td = rng.uniform(0, np.pi / 2, (2, 1000))
    pd, ph = rng.uniform(-np.pi, np.pi, (2, 1000))
    wi, wo = merl.directions(th, td, pd, ph)
    th2, td2, pd2 = merl.half_diff(wi, wo)
    assert np.allclose(th2, th, atol=1e-9) and np.allclose(td2, td, atol=1e-9)
    assert np.allclose(np.exp(1j * pd2), np.exp(1j * pd), atol=1e-9)


def test_bin_index_reciprocity_and_merl_rules():
    wi, wo = _random_pairs(20000, seed=3)
    a = merl.flat_index(wi, wo)
    b = merl.flat_index(wo, wi)
    assert np.array_equal(a, b)
    # MERL's reference indexing on hand-chosen values
    i_h, i_d, i_p = merl.bin_index(
        np.array([0.0, (0.5**2) * np.pi / 2, np.pi / 2, 2.0, -0.1]),
        np.array([0.0, np.pi / 4, np.pi / 2, 0.01, 0.0]),
        np.array([-np.pi / 2, np.pi / 2, np.pi, -1e-9, 3 * np.pi / 2]),
    )
    assert i_h.tolist() == [0, 45, 89, 89, 0]
    assert i_d.tolist() == [0, 45, 89, 0, 0]
    assert i_p.tolist() == [90, 90, 0, 179, 90]


def test_bin_centres_map_back_to_their_bins():
    dims = (12, 10, 20)
    th, td, pd = merl.bin_centres(dims)
    i_h, i_d, i_p = merl.bin_index(th, td, pd, dims)
    grid = np.meshgrid(*(np.arange(n) for n in dims), indexing="ij")
    assert all(np.array_equal(a, g) for a, g in zip((i_h, i_d, i_p), grid))


def test_above_horizon_mask_matches_directions():
    dims = (20, 20, 40)
    mask = merl.above_horizon(dims)
    wi, wo = merl.directions(*merl.bin_centres(dims))
    assert np.array_equal(mask, (wi[..., 2] > 0) & (wo[..., 2] > 0))
    assert 0.5 < mask.mean() < 0.9


def test_filled_reflectance_convention():
    dims = (10, 10, 20)
    mask = merl.above_horizon(dims)
    raw = np.where(mask, 300.0, -1.0)[None].repeat(3, axis=0)
    raw[1] *= 2
    hole = tuple(np.argwhere(mask)[len(np.argwhere(mask)) // 2])
    raw[(0,) + hole] = -1.0  # unmeasured above the horizon: nearest value
    refl = merl.filled_reflectance(raw)
    assert refl.dtype == np.float32
    assert np.all(refl[:, ~mask] == 0)
    assert refl[(0,) + hole] == pytest.approx(300.0 * merl.SCALE[0])
    assert np.allclose(refl[1][mask], 600.0 * merl.SCALE[1])
    with pytest.raises(ValueError, match="no measured bin"):
        merl.filled_reflectance(np.full((3,) + dims, -1.0))
