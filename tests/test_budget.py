"""The one search to a byte budget (training/budget.py): the largest lattice point whose size fits."""

import numpy as np
import pytest

from apmgsrn.training.budget import coded_budget, largest_fitting, overhead_bytes


@pytest.mark.parametrize("seed", range(20))
def test_the_search_finds_the_largest_fitting_point_of_any_growing_size(seed):
    """Sizes that grow with the lattice point at random rates (straight, curved, with flat runs): the search
    returns the point brute force finds, with its size, and asks no point twice."""
    rng = np.random.default_rng(seed)
    points = int(rng.integers(2, 600))
    growth = rng.exponential(1.0, points) ** rng.uniform(0.2, 3.0) * (rng.random(points) > 0.1)
    sizes = np.cumsum(growth * 100).astype(np.int64) + int(rng.integers(0, 1000))
    low, high = 0, points - 1
    budget = int(rng.integers(sizes[0], sizes[high])) if sizes[high] > sizes[0] else int(sizes[0])
    if sizes[high] <= budget:
        budget = int(sizes[high]) - 1
    asked = []

    def size(k):
        asked.append(k)
        return int(sizes[k])

    found = largest_fitting(size, budget, low, high, int(sizes[high]))
    fitting = np.flatnonzero(sizes[:high] <= budget)
    if fitting.size == 0:
        assert found is None
    else:
        assert found == (int(fitting[-1]), int(sizes[fitting[-1]]))
    assert len(asked) == len(set(asked)) and all(low <= k < high for k in asked)


def test_nothing_fits_and_empty_brackets():
    assert largest_fitting(lambda k: 10 + k, 5, 0, 8, 18) is None
    assert largest_fitting(lambda k: k, 5, 3, 3, 9) is None
    assert largest_fitting(lambda k: k, 5, 0, 9, 9) == (5, 5)


def test_the_overhead_is_what_the_sections_leave():
    assert overhead_bytes(1000, [b"x" * 300, b"y" * 200]) == 500
    assert coded_budget(1000, 500) == 500 and coded_budget(100, 500) == 1
