"""The points a blend takes, one per target of its basis, checked before any image is read."""

from types import SimpleNamespace

import numpy as np
import pytest

from mitsuba_manifold.basis.outputs import Output, check_steps, frame_names, planned_files
from mitsuba_manifold.basis.points import path_end, target_index, target_points
from mitsuba_manifold.errors import InputError, MismatchError


class _Manifold:
    """Two materials on a 2-D latent space (only what the point rules read)."""

    q = 2
    names = ["gold", "steel"]
    latent = np.array([[0.5, -0.5], [-1.0, 1.0]])

    def point(self, name):
        return self.latent[self.names.index(name)]


def _basis(*targets):
    return SimpleNamespace(p=len(targets), targets=list(targets), resolution=(8, 8))


def test_one_point_per_target_names_resolved():
    m = _Manifold()
    assert target_points(_basis("a"), m, ["steel"]) == [-1.0, 1.0]
    assert target_points(_basis("a", "b"), m, [[0.1, 0.2], "gold"]) == [0.1, 0.2, 0.5, -0.5]
    with pytest.raises(MismatchError, match="`x` needs 2 numbers"):
        target_points(_basis("a"), m, [[0.1, 0.2, 0.3]])
    with pytest.raises(MismatchError, match="`x` is given 2 times"):
        target_points(_basis("a"), m, ["gold", "steel"])
    with pytest.raises(MismatchError, match="repeat `x` once per target, in this order"):
        target_points(_basis("a", "b"), m, ["gold"])


def test_along_a_path_the_fixed_targets_take_the_points_and_the_moving_one_is_filled_in():
    m, basis = _Manifold(), _basis("a", "b", "c")
    got = target_points(basis, m, ["steel", [0.0, 0.0]], path=True, moving="b")
    assert got == [-1.0, 1.0, 0.5, -0.5, 0.0, 0.0]  # row 1 (b) is the path's
    assert target_index(basis, "c") == 2 and target_index(basis, None) == 0
    with pytest.raises(MismatchError, match="`target` 'd' is not a target"):
        target_points(basis, m, ["gold", "gold"], path=True, moving="d")
    with pytest.raises(MismatchError, match=r"give one `x` per target that stays fixed \(b, c, in"):
        target_points(basis, m, None, path=True)
    with pytest.raises(MismatchError, match="drop `x`"):
        target_points(_basis("a"), m, ["gold"], path=True)
    assert target_points(_basis("a"), m, None, path=True) is None


def test_path_ends_are_names_or_q_finite_numbers():
    m = _Manifold()
    assert path_end(m, "gold") == "gold" and path_end(m, [0.1, 0.2]) == [0.1, 0.2]
    for bad in ([0.1], [0.1, float("nan")]):
        with pytest.raises(MismatchError, match="`path` end '0,x' must be a material name or 2"):
            path_end(m, bad, given="0,x")


def test_a_blend_names_every_file_it_writes_before_any_work(tmp_path):
    out = Output(str(tmp_path / "img.exr"), png=True)
    kinds = [k for k, _ in planned_files(out, render_reference=True)]
    assert kinds == ["image", "png", "reference", "reference PNG", "error image", "error PNG"]
    assert [k for k, _ in planned_files(Output(str(tmp_path / "i.exr")))] == ["image"]
    (tmp_path / "seq_07.exr").write_bytes(b"")
    path = planned_files(Output(str(tmp_path / "seq.exr")), path_steps=12)
    assert path[0] == ("image", str(tmp_path / "seq_00.exr"))
    assert ("frame", str(tmp_path / "seq_07.exr")) in path
    assert path[-1] == ("contact sheet", str(tmp_path / "seq_sheet.png"))
    assert frame_names(Output("s.exr"), 3) == ["s_0.exr", "s_1.exr", "s_2.exr"]
    with pytest.raises(InputError, match="`out` must name an .exr file"):
        Output("img.png").check()
    with pytest.raises(InputError, match="`steps` must be from 2"):
        check_steps(1)


def test_a_basis_render_refuses_settings_whose_seeds_overflow():
    from mitsuba_manifold.basis.sampling import check_sampling

    check_sampling(64, chunks=4, mode="onepass", seed=1000)
    with pytest.raises(InputError, match="`spp` 0 is not allowed"):
        check_sampling(0)
    with pytest.raises(InputError, match="`max_depth` must be -1"):
        check_sampling(4, max_depth=1)
    with pytest.raises(
        InputError, match=r"`seed` must be an integer .* with `spp` 4096, `chunks` 2"
    ):
        check_sampling(4096, chunks=2, seed=2**31)
