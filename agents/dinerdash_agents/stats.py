"""The statistics the results table rests on (Agarwal et al. 2021, "Deep RL at the Edge of the
Statistical Precipice"): per agent the mean over its training seeds, the interquartile mean over
all its evaluation episodes, and a 95 % bootstrap confidence interval of its fraction of the
expert, paired on the evaluation seeds.

The data of one agent is a matrix ``scores`` (R, N): one row per training seed (run), one column
per evaluation seed; the expert played the same N seeds (``expert``, (N,)).

- ``fraction = mean(scores) / mean(expert)``: the mean over runs and episodes (the same as the
  mean over runs of each run's mean) over the expert's mean.
- The interval resamples the **evaluation seeds** with replacement, the agent's column (its runs'
  mean on that seed) and the expert's score on the same seed together (``paired=True``), so the
  seeds' shared difficulty cancels from the ratio: a hard seed is hard for both. The runs are
  not resampled: with 1 to 5 training seeds a bootstrap over them is meaningless; their spread
  is reported beside the interval (each run's own fraction).
- BCa intervals (bias-corrected and accelerated), 10,000 resamples, a fixed generator seed so the
  table is reproducible.

``scipy.stats.bootstrap`` does the resampling (scipy is maintained, already installed with JAX,
and its ``paired=True`` is exactly this design). rliable was not used: it pins old versions of
``arch`` and pulls ``seaborn``/``pandas``, and its stratified bootstrap resamples runs within
tasks, which does not fit one task with paired evaluation seeds.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from scipy import stats as _scipy_stats

__all__ = ["AgentStats", "agent_stats", "difference_interval", "fraction_interval", "iqm"]

#: Resamples of each bootstrap interval, and the generator seed that makes them reproducible.
RESAMPLES = 10_000
BOOTSTRAP_SEED = 0
CONFIDENCE = 0.95


def iqm(values: Any) -> float:
    """The interquartile mean: the mean of the middle 50 % of ``values`` (flattened), the lowest
    and the highest 25 % cut off (``scipy.stats.trim_mean(x, 0.25)``, as rliable's IQM)."""
    x = np.asarray(values, np.float64).reshape(-1)
    if x.size == 0:
        raise ValueError("iqm of no values")
    return float(_scipy_stats.trim_mean(x, 0.25))


def _ratio(agent: np.ndarray, expert: np.ndarray, axis: int = -1) -> np.ndarray:
    return np.mean(agent, axis=axis) / np.mean(expert, axis=axis)


def _per_seed(scores: Any) -> np.ndarray:
    """``scores`` (N,), or (R, N) averaged over its R runs seed by seed, as float64."""
    x = np.asarray(scores, np.float64)
    return x.mean(axis=0) if x.ndim == 2 else x


def _expert_scores(expert: Any) -> np.ndarray:
    expert = np.asarray(expert, np.float64)
    if np.mean(expert) <= 0:
        raise ValueError("the expert's mean must be positive to take fractions of it")
    return expert


def _paired_interval(
    samples: tuple[np.ndarray, ...],
    statistic: Any,
    confidence: float,
    resamples: int,
    seed: int,
    method: str,
) -> tuple[float, float]:
    """The ``confidence`` bootstrap interval of ``statistic(*samples)``, the samples' values on
    one evaluation seed resampled together (``paired=True``)."""
    result = _scipy_stats.bootstrap(
        samples,
        statistic,
        paired=True,
        vectorized=True,
        n_resamples=resamples,
        confidence_level=confidence,
        method=method,
        random_state=np.random.default_rng(seed),
    )
    low, high = result.confidence_interval
    return float(low), float(high)


def fraction_interval(
    scores: Any,
    expert: Any,
    *,
    confidence: float = CONFIDENCE,
    resamples: int = RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
    method: str = "BCa",
) -> tuple[float, float]:
    """The ``confidence`` bootstrap interval of ``mean(scores) / mean(expert)``, resampling the
    evaluation seeds: ``scores`` (N,) or (R, N) (R runs on the same N seeds; a seed's column is
    averaged over the runs first), ``expert`` (N,), paired seed by seed."""
    agent, expert = _per_seed(scores), np.asarray(expert, np.float64)
    if agent.ndim != 1 or agent.shape != expert.shape:
        raise ValueError(f"scores {np.shape(scores)} do not pair with expert {expert.shape}")
    if len(agent) < 2:
        raise ValueError("a bootstrap interval needs at least 2 evaluation seeds")
    expert = _expert_scores(expert)
    point = float(_ratio(agent, expert))
    if np.allclose(agent, point * expert):
        # Every resample's ratio is the same (BCa's acceleration is then 0/0): the interval is
        # the point.
        return point, point
    return _paired_interval((agent, expert), _ratio, confidence, resamples, seed, method)


def _difference(a: np.ndarray, b: np.ndarray, expert: np.ndarray, axis: int = -1) -> np.ndarray:
    return (np.mean(a, axis=axis) - np.mean(b, axis=axis)) / np.mean(expert, axis=axis)


def difference_interval(
    scores_a: Any,
    scores_b: Any,
    expert: Any,
    *,
    confidence: float = CONFIDENCE,
    resamples: int = RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> tuple[float, float, float]:
    """How much more of the expert agent A scores than agent B: ``(mean(A) - mean(B)) /
    mean(expert)`` and its ``confidence`` BCa interval, resampling the evaluation seeds with A's,
    B's and the expert's scores on a seed kept together (all three played the same seeds).
    ``scores_a``, ``scores_b``: (N,) or (R, N) (runs averaged per seed first); returns (point,
    low, high)."""
    a, b, expert = _per_seed(scores_a), _per_seed(scores_b), np.asarray(expert, np.float64)
    if not a.shape == b.shape == expert.shape or a.ndim != 1:
        raise ValueError(
            f"{np.shape(scores_a)}, {np.shape(scores_b)} and {expert.shape} do not pair"
        )
    expert = _expert_scores(expert)
    low, high = _paired_interval((a, b, expert), _difference, confidence, resamples, seed, "BCa")
    return float(_difference(a, b, expert)), low, high


@dataclass(frozen=True)
class AgentStats:
    """One agent's figures for the results table."""

    #: Training seeds (runs) the figures pool.
    runs: int
    #: Mean score over runs and evaluation episodes (= the mean over runs of each run's mean).
    mean: float
    #: Interquartile mean over all R × N evaluation episodes.
    iqm: float
    #: ``mean`` over the expert's mean on the same seeds, and its paired 95 % interval.
    fraction: float
    fraction_low: float
    fraction_high: float
    #: Each run's own fraction of the expert (its spread over training seeds), and their median.
    run_fractions: tuple[float, ...]
    median_run_fraction: float

    def to_json(self) -> dict[str, Any]:
        return {
            k: (list(v) if isinstance(v, tuple) else round(v, 6) if isinstance(v, float) else v)
            for k, v in asdict(self).items()
        }


def agent_stats(scores: Any, expert: Any, **interval: Any) -> AgentStats:
    """:class:`AgentStats` of ``scores`` ((N,) for one run, (R, N) for R runs) against the
    expert's ``expert`` (N,) on the same evaluation seeds; ``interval``: keywords of
    :func:`fraction_interval`."""
    runs = np.asarray(scores, np.float64)
    if runs.ndim == 1:
        runs = runs[None]
    expert = np.asarray(expert, np.float64)
    low, high = fraction_interval(runs, expert, **interval)
    run_fractions = tuple(float(f) for f in runs.mean(axis=1) / expert.mean())
    return AgentStats(
        runs=len(runs),
        mean=float(runs.mean()),
        iqm=iqm(runs),
        fraction=float(runs.mean() / expert.mean()),
        fraction_low=low,
        fraction_high=high,
        run_fractions=run_fractions,
        median_run_fraction=float(np.median(run_fractions)),
    )
