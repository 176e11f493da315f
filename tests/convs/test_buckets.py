"""fwk.graph.buckets: rows cut into at most k groups with the least padding (against brute force)."""
import itertools

import numpy as np
import pytest

from fwk.graph import buckets


def brute(counts, k):
    s = np.sort(counts)
    best = None
    for m in range(1, k + 1):
        for cuts in itertools.combinations(range(1, len(s)), m - 1):
            edges = [0, *cuts, len(s)]
            cost = sum((e - a) * max(1, s[e - 1]) for a, e in zip(edges, edges[1:]))
            best = cost if best is None else min(best, cost)
    return best


@pytest.mark.parametrize("seed", range(20))
def test_buckets_pad_least_and_partition_the_rows(seed):
    rng = np.random.default_rng(seed)
    counts = rng.integers(0, 12, size=rng.integers(1, 9))
    k = int(rng.integers(1, 5))
    order, spans = buckets(counts, k)
    assert sorted(order.tolist()) == list(range(len(counts)))
    assert len(spans) <= k
    assert spans[0][0] == 0 and sum(c for _, c, _ in spans) == len(counts)
    for start, count, width in spans:
        assert width >= 1 and all(counts[r] <= width for r in order[start:start + count])
    assert sum(c * w for _, c, w in spans) == brute(counts, k)
