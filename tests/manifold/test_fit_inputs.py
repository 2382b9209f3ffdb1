"""Manifold.fit's arguments as users give them: a comma-separated `names`, a table's path for the
folder, a bool for a number, and a database too coarse to fit are refused (or read) clearly, before
any fit and never by saving a manifold no reader takes."""

import os

import numpy as np
import pytest

from mitsuba_manifold.errors import InputError
from mitsuba_manifold.manifold.model import Manifold


def test_names_as_one_comma_separated_text(small_db):
    m = Manifold.fit(small_db, q=2, names="chrome, steel,gold-paint", max_iter=5)
    assert m.names == ["chrome", "steel", "gold-paint"]


def test_a_table_file_for_the_database_folder_says_what_to_pass(small_db):
    with pytest.raises(
        InputError,
        match=r"is a file, not a folder; pass the folder .*" + os.path.basename(small_db),
    ):
        Manifold.fit(os.path.join(small_db, "chrome.binary"))


@pytest.mark.parametrize("key", ["power", "taper", "spread"])
def test_a_bool_is_not_a_number_of_the_interpolant(small_db, key):
    with pytest.raises(InputError, match=f"`{key}` must be a number, got True"):
        Manifold.fit(small_db, q=2, interpolant={"kind": "shepard", key: True}, max_iter=5)


def test_a_database_of_one_bin_tables_is_refused_before_fitting(tmp_path):
    for i, name in enumerate(["a", "b", "c"]):
        with open(tmp_path / f"{name}.binary", "wb") as f:
            np.array([1, 1, 1], np.int32).tofile(f)
            np.full(3, 0.1 * (i + 1)).tofile(f)
    with pytest.raises(InputError, match="1x1x1 bins .* use tables of more bins"):
        Manifold.fit(str(tmp_path), q=2)


def test_fit_options_refuse_a_method_that_cannot_fit_the_stress_term():
    from mitsuba_manifold.manifold.presets import FitOptions

    assert FitOptions(preset="paper").check().given() == ["`preset`"]
    assert FitOptions(q=3, stress=0.0).given() == ["`q`", "`stress`"]
    with pytest.raises(InputError, match="`method` hooke-jeeves cannot fit .* the default preset"):
        FitOptions(method="hooke-jeeves").check()
    FitOptions(method="hooke-jeeves", stress=0.0).check()
    with pytest.raises(InputError, match="`q` must be an integer from 1 to 8"):
        FitOptions(q=9).check()
