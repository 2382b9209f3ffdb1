"""The Fig. 9 benchmark's report of every neighbour pair."""

import pytest

from benchmarks import fig9
from mitsuba_manifold.manifold import space
from mitsuba_manifold.manifold.model import Manifold


@pytest.fixture(scope="module")
def m(small_manifold):
    return Manifold.load(small_manifold)


def test_fig9_every_neighbour_pair_measures_each_pair_once(m):
    rep = fig9.every_pair_report(m, progress=False)
    want = [[m.names[i], m.names[j]] for i, j in space.all_neighbour_pairs(m.latent)]
    assert [r["pair"] for r in rep["rows"]] == want
    assert rep["largest_step"] == max(r["largest_step"] for r in rep["rows"]) <= 1.0
    assert rep["steps_over_target"] == sum(
        r["largest_step"] > fig9.TARGETS["largest_step"] for r in rep["rows"]
    )
