"""Denoised blends: directional albedos (NumPy), first-hit AOVs and OIDN lowering the error
(issue 13; rendered, ``render`` marker)."""

import os

import numpy as np
import pytest

from mitsuba_manifold import errors
from mitsuba_manifold.basis import denoise
from mitsuba_manifold.basis.blend import denoised_blend
from mitsuba_manifold.basis.folder import manifest
from mitsuba_manifold.data import merl
from mitsuba_manifold.data.database import Database
from mitsuba_manifold.imaging import metrics
from mitsuba_manifold.manifold.model import Manifold


def test_directional_albedo_of_lambertian_tables(tmp_path):
    dims = (16, 16, 32)
    rho = {"grey": (0.2, 0.5, 0.8), "white": (0.9, 0.9, 0.9)}
    for name, r in rho.items():
        refl = np.ones((3,) + dims) * np.asarray(r)[:, None, None, None] / np.pi
        merl.write_binary(str(tmp_path / f"{name}.binary"), merl.to_stored(refl))
    db = Database(str(tmp_path))
    a = denoise.directional_albedos(db, ["grey", "white"], bins=9)
    assert a.shape == (2, 9, 3)
    np.testing.assert_allclose(a[0], np.tile([0.2, 0.5, 0.8], (9, 1)), rtol=0.03)
    np.testing.assert_allclose(a[1], 0.9, rtol=0.03)


def test_restored_light_keeps_every_channel_total_and_spreads_a_firefly():
    """What a denoiser took (a firefly, signed cross-term light) comes back with each channel's
    total exactly, spread over about an eighth of the image: no pixel gets a firefly back."""
    removed = np.zeros((48, 64, 3), np.float32)
    removed[2, 3] = (900.0, 0.0, 30.0)  # near a corner: the edges keep the light too
    removed[30, 40, 1] = -60.0  # a negative part (cross terms)
    back = denoise.restore_light(removed)
    np.testing.assert_allclose(
        back.sum(axis=(0, 1)), removed.sum(axis=(0, 1)), rtol=1e-4, atol=1e-3
    )
    assert back[..., 0].max() < 0.02 * 900.0 and back[..., 0].min() >= 0.0
    assert back[..., 1].min() < 0.0 and back[..., 1].max() <= 0.0
    wide = np.count_nonzero(back[..., 0] > 0.5 * back[..., 0].max())
    assert 20 < wide < 0.25 * 48 * 64, wide  # spread, not everywhere
    assert (
        back[-1, -1, 0] < 1e-3 * back[..., 0].max()
    )  # near where it was taken, not across the image


@pytest.mark.render
def test_denoised_blend_beats_raw_and_aovs_are_checked(tmp_path, small_manifold):
    mi = pytest.importorskip("mitsuba")
    pytest.importorskip("pyoidn")
    import mitsuba_manifold
    from mitsuba_manifold.render.jobs import render_basis
    from mitsuba_manifold.render.scene import scenes

    mi.set_variant("llvm_ad_rgb")
    mitsuba_manifold.register()
    TABLE = scenes.scene_path("table")
    m = Manifold.load(small_manifold)
    out = str(tmp_path / "b")
    names = ["gold-paint", "chrome", "pink-fabric", "white-diffuse-bball"]
    render_basis.render_basis(
        TABLE, small_manifold, out, spp=4, mode="onepass", resolution=48, materials=names, aovs=True
    )
    aovs = denoise.BasisAOVs.load(out, manifest.Manifest.read(out))
    hit = aovs.hist.sum(-1)
    assert hit.min() >= 0 and hit.max() <= 1 + 1e-5 and (hit > 0.99).sum() > 50  # the bowl
    n = np.linalg.norm(aovs.normal, axis=-1)
    assert np.all(n <= 1 + 1e-4) and (n > 0.99).mean() > 0.5
    # albedo: base (table, where the bowl is not) plus the weighted material albedos
    one = aovs.albedo({"white-diffuse-bball": 1.0})
    half = aovs.albedo({"white-diffuse-bball": 0.5, "chrome": 0.5})
    bowl = hit > 0.99
    expect = 0.5 * (one[bowl] + aovs.albedo({"chrome": 1.0})[bowl])
    np.testing.assert_allclose(half[bowl], expect, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(
        one[~bowl & (hit == 0)], aovs.albedo_base[~bowl & (hit == 0)].clip(0, 1)
    )

    x = 0.5 * (m.latent[m.index("gold-paint")] + m.latent[m.index("chrome")])
    ref = scenes.render_reference(TABLE, small_manifold, x, 256, resolution=48)
    raw, den, info = denoised_blend(out, m, x=x, prune=0.0, renormalise=True)
    e_raw, e_den = metrics.compare(raw, ref)["rel_mse"], metrics.compare(den, ref)["rel_mse"]
    assert info.guided and e_den < 0.5 * e_raw, (e_raw, e_den)

    # AOVs of another basis are refused
    other = str(tmp_path / "other")
    render_basis.render_basis(
        TABLE, small_manifold, other, spp=1, mode="onepass", resolution=32, materials=names
    )
    os.replace(os.path.join(out, denoise.AOV_FILE), os.path.join(other, denoise.AOV_FILE))
    with pytest.raises(errors.MismatchError, match="another basis .*resolution"):
        denoised_blend(other, m, x=x, prune=0.0, renormalise=True)
    with pytest.raises(errors.MismatchError, match="no aovs.npz"):
        denoise.BasisAOVs.load(out)
    with open(
        os.path.join(out, denoise.AOV_FILE), "wb"
    ) as f:  # not an archive: no NumPy pickle advice
        f.write(b"\x93NUMPY\x01\x00garbage")
    with pytest.raises(
        errors.MismatchError, match="is not an AOV file written by render_basis"
    ) as e:
        denoise.BasisAOVs.load(out)
    assert "pickle" not in str(e.value)
