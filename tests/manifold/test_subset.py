"""A manifold of some of a manifold's materials (:meth:`Manifold.subset`)."""

import numpy as np
import pytest

from mitsuba_manifold.errors import InputError
from mitsuba_manifold.manifold.model import Manifold


def test_a_subset_keeps_the_weights_and_tables_of_the_full_manifold(small_manifold, tmp_path):
    """A subset is fit on its own centred Gram block but keeps the full manifold's interpolant
    (the default's convex weights), not Manifold's own default (Eq. 4)."""
    full = Manifold.load(small_manifold)
    names = full.names[:-1]
    sub = full.subset(names)
    assert (
        sub.names == names
        and sub.hashes == full.hashes[:-1]
        and sub.latent.shape == (full.n - 1, full.q)
    )
    assert (
        sub.interpolant.params() == full.interpolant.params() and sub.interpolant.kind == "shepard"
    )
    assert np.array_equal(sub.table_gram, full.table_gram[:-1, :-1])
    assert np.allclose(sub.gram.sum(axis=0), 0.0, atol=1e-8 * np.abs(sub.gram).max())  # centred
    # at a training point the subset's weights pick that material alone, as the full manifold's do
    _, w = sub.weights(sub.latent[0])
    assert w[0] == pytest.approx(1.0, abs=1e-6)
    sub.save(tmp_path / "sub.npz")
    again = Manifold.load(tmp_path / "sub.npz")
    assert again.names == names and again.info["subset_of"] == small_manifold
    assert np.array_equal(again.latent, sub.latent)


@pytest.mark.parametrize(
    "names, words",
    [
        (["chrome", "nope"], "unknown material 'nope'"),
        (["chrome"], "at least two distinct"),
        (["chrome", "chrome"], "at least two distinct"),
    ],
)
def test_a_subset_of_unknown_or_too_few_materials_is_refused(small_manifold, names, words):
    full = Manifold.load(small_manifold)
    names = [full.names[0] if n == "chrome" else n for n in names]
    with pytest.raises(InputError, match=words.replace("'chrome'", repr(full.names[0]))):
        full.subset(names)
