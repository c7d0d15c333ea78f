"""The results table's statistics on synthetic data with known answers: the interquartile mean of
known arrays, the paired interval's coverage of a known ratio, pairing's narrower interval, and
the pooling of several training seeds."""

from __future__ import annotations

import numpy as np
import pytest

from dinerdash_agents.stats import agent_stats, difference_interval, fraction_interval, iqm


def test_iqm_of_known_arrays() -> None:
    # 8 values: the lowest 2 and the highest 2 are cut, the mean of 3, 4, 5, 6 is 4.5.
    assert iqm([1, 2, 3, 4, 5, 6, 7, 8]) == pytest.approx(4.5)
    # Outliers in the outer quarters do not move it.
    assert iqm([-1e9, 2, 3, 4, 5, 6, 7, 1e9]) == pytest.approx(4.5)
    # A matrix is flattened: all runs' episodes together.
    assert iqm(np.arange(1, 9).reshape(2, 4)) == pytest.approx(4.5)
    with pytest.raises(ValueError):
        iqm([])


def test_the_paired_interval_contains_the_true_ratio_and_is_narrower_than_unpaired() -> None:
    # Seeds of very different difficulty; the agent scores 1.1 × the expert on each, with small
    # independent noise. The true ratio of means is 1.1.
    rng = np.random.default_rng(1)
    difficulty = rng.uniform(2_000, 20_000, size=100)
    expert = difficulty + rng.normal(0, 300, size=100)
    agent = 1.1 * difficulty + rng.normal(0, 300, size=100)
    low, high = fraction_interval(agent, expert)
    assert low < 1.1 < high
    assert high - low < 0.03  # the seeds' difficulty cancels out of the paired ratio
    # Shuffling the expert's scores breaks the pairing: the same data, a far wider interval.
    unpaired_low, unpaired_high = fraction_interval(agent, rng.permutation(expert))
    assert unpaired_high - unpaired_low > 5 * (high - low)


def test_coverage_of_the_95_percent_interval_is_near_95_percent() -> None:
    # 100 synthetic experiments with a known ratio 1.2 and noisy pairs: the interval should
    # miss it about 5 times (allowing 0..12: a binomial's 99.9 % range for p = 0.05, n = 100).
    rng = np.random.default_rng(7)
    misses = 0
    for _ in range(100):
        difficulty = rng.uniform(1_000, 10_000, size=60)
        expert = difficulty * rng.lognormal(0, 0.3, size=60)
        agent = 1.2 * difficulty * rng.lognormal(0, 0.3, size=60)
        # The ratio of the population means is 1.2 (the noise factors have equal means).
        low, high = fraction_interval(agent, expert, resamples=2_000)
        misses += not low < 1.2 < high
    assert misses <= 12


def test_the_paired_difference_of_two_agents_holds_the_true_one() -> None:
    # Two agents and the expert on the same seeds of very different difficulty: A scores 1.10 and
    # B 1.05 of the expert on each (small independent noise): the true difference is 0.05.
    rng = np.random.default_rng(3)
    difficulty = rng.uniform(2_000, 20_000, size=100)
    expert, a, b = (f * difficulty + rng.normal(0, 300, size=100) for f in (1.0, 1.10, 1.05))
    point, low, high = difference_interval(a, b, expert)
    assert low < 0.05 < high and low < point < high
    assert high - low < 0.03  # paired: the seeds' difficulty cancels from the difference
    # Runs (R, N) are averaged per seed; swapping the agents negates the difference.
    runs = np.stack([a - 50, a + 50])
    assert difference_interval(runs, b, expert)[0] == pytest.approx(point)
    swapped = difference_interval(b, a, expert)
    assert swapped == pytest.approx((-point, -high, -low), abs=2e-3)
    with pytest.raises(ValueError, match="pair"):
        difference_interval(a, b[:50], expert)


def test_agent_stats_pools_training_seeds() -> None:
    expert = np.array([100.0, 200, 300, 400])
    runs = np.array([[110.0, 220, 330, 440], [90.0, 180, 270, 360], [100.0, 200, 300, 400]])
    s = agent_stats(runs, expert)
    assert s.runs == 3
    assert s.mean == pytest.approx(250.0)
    assert s.fraction == pytest.approx(1.0)
    assert s.run_fractions == pytest.approx((1.1, 0.9, 1.0))
    assert s.median_run_fraction == pytest.approx(1.0)
    # Middle half of the 12 pooled scores: 3 cut at each end.
    assert s.iqm == pytest.approx(np.mean(np.sort(runs.reshape(-1))[3:9]))
    # The runs' mean on each seed is exactly the expert's score: every resample's ratio is 1.
    assert s.fraction_low == pytest.approx(1.0)
    assert s.fraction_high == pytest.approx(1.0)
    # Noisy runs: the interval holds the point estimate.
    noisy = agent_stats(runs + np.array([[5.0, -20, 10, 0]]), expert)
    assert noisy.fraction_low < noisy.fraction < noisy.fraction_high
    json = s.to_json()
    assert json["runs"] == 3 and json["run_fractions"] == pytest.approx([1.1, 0.9, 1.0])
    # One run: (N,) is one row.
    assert agent_stats(runs[0], expert).fraction == pytest.approx(1.1)


def test_refusals() -> None:
    with pytest.raises(ValueError, match="pair"):
        fraction_interval([1.0, 2.0, 3.0], [1.0, 2.0])
    with pytest.raises(ValueError, match="positive"):
        fraction_interval([1.0, 2.0], [-1.0, -2.0])
