"""Connected components from edges taken batch by batch (`components.JoinedComponents`)."""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from app.pipelines.guardrail.components import JoinedComponents


def test_batches_give_the_components_of_all_edges_at_once() -> None:
    """Random edges in five batches: the same components, numbered alike (in order of their
    first point), as scipy's on every edge at once; isolated points are components of one."""
    rng = np.random.default_rng(7)
    n = 5_000
    i, j = rng.integers(0, n, 3_000), rng.integers(0, n, 3_000)
    joined = JoinedComponents(n)
    for part in np.array_split(np.arange(len(i)), 5):
        joined.add(i[part], j[part])
    joined.add(np.zeros(0, np.int64), np.zeros(0, np.int64))  # an empty batch changes nothing
    graph = coo_matrix((np.ones(len(i)), (i, j)), shape=(n, n))
    count, expected = connected_components(graph, directed=False)
    assert np.array_equal(joined.labels(), expected)
    assert joined.labels().max() + 1 == count
