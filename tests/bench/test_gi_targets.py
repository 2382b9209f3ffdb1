"""The GI-targets benchmark's machinery at a tiny size: its report holds each scene's bases and
every point's blends against the reference."""

import pytest

from benchmarks import gi


@pytest.mark.render
def test_the_gi_targets_report_holds_the_bases_and_every_points_blends(
    small_db, small_manifold, tmp_path
):
    report = gi.targets(
        small_db,
        manifold=small_manifold,
        scenes=("sphere",),
        res=8,
        basis_spp=2,
        ref_spp=4,
        direct_spp=2,
        out=str(tmp_path / "out"),
        log=None,
    )
    scene = report["scenes"]["sphere"]
    assert "l1" in scene["basis_gi"]["components"] and scene["basis_gi"]["bytes"] > 0
    assert [p["point"] for p in scene["points"]] == ["training", "midpoint", "extrapolated"]
    for p in scene["points"]:
        for part in ("l1", "full", "full_summed", "direct", "refined"):
            assert p[part]["rel_mse"] >= 0
