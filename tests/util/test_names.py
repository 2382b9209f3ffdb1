"""Material names as file stems: a material named like another's full-GI image gets its own file."""

from mitsuba_manifold._util.names import escape, is_escaped, unescape

GI_SUFFIX = (
    ".gi.exr"  # the full-GI image of a material (render/jobs/gi_basis.py; no Mitsuba import here)
)


def test_a_name_ending_in_gi_does_not_take_another_materials_full_gi_file():
    names = ["steel", "steel.gi", "Steel.GI", "a.gi.gi", "steel%2Egi", "gi"]
    l1_files = {escape(n) + ".exr" for n in names}
    gi_files = {escape(n) + GI_SUFFIX for n in names}
    assert len(l1_files) == len(names) and not l1_files & gi_files
    for n in names:
        assert unescape(escape(n)) == n and is_escaped(escape(n))
    assert escape("gold-paint") == "gold-paint" and escape("gi") == "gi"  # common names unchanged
