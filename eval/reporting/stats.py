"""The report's statistics, in one place: the percentile bootstrap of a mean (every table's
interval), the interquartile mean and the stratified bootstrap over environments (the
science study's aggregate, as rliable computes them). Deterministic: a fixed seed."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import numpy as np

BOOTSTRAP = 2000
"""Bootstrap resamples of every interval."""
CI_SEED = 0
"""Seed of every bootstrap (intervals are reproducible)."""


def bootstrap_ci(values, resamples: int = BOOTSTRAP, seed: int = CI_SEED) -> tuple[float, float, float, int]:
    """(mean, low, high, n) of the finite values: a 95% percentile bootstrap of the mean.

    Deterministic (a fixed seed); n = 1 gives an interval of zero width, n = 0 NaNs.
    """
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    n = len(v)
    if n == 0:
        return float("nan"), float("nan"), float("nan"), 0
    mean = float(v.mean())
    if n == 1:
        return mean, mean, mean, 1
    rng = np.random.default_rng(seed)
    means = v[rng.integers(0, n, (resamples, n))].mean(axis=1)
    lo, hi = np.percentile(means, [2.5, 97.5])
    return mean, float(lo), float(hi), n


def iqm(scores, axis: int | None = None):
    """Interquartile mean: the mean of the middle half after cutting floor(n/4) values at
    each end (scipy.stats.trim_mean(x, 0.25), what rliable's ``aggregate_iqm`` returns)."""
    x = np.asarray(scores, float)
    if axis is None:
        x, axis = x.ravel(), 0
    x = np.sort(np.moveaxis(x, axis, -1), axis=-1)
    n = x.shape[-1]
    if n == 0:
        raise ValueError("iqm of no scores")
    k = int(0.25 * n)
    return x[..., k:n - k].mean(axis=-1)


def stratified_bootstrap(scores: Mapping[str, Sequence[float]],
                         statistic: Callable = iqm, resamples: int = BOOTSTRAP,
                         seed: int = CI_SEED) -> tuple[float, float, float]:
    """(point, low, high): the statistic of every task's runs pooled, and its 95% percentile
    interval when each task's runs (seeds) are resampled with replacement separately
    (rliable's stratified bootstrap; tasks = environments)."""
    tasks = [np.asarray(v, float) for v in scores.values()]
    if not tasks or any(len(v) == 0 for v in tasks):
        raise ValueError("stratified_bootstrap needs at least one score per task")
    point = float(statistic(np.concatenate(tasks)))
    rng = np.random.default_rng(seed)
    draws = np.concatenate([v[rng.integers(0, len(v), (resamples, len(v)))] for v in tasks], axis=1)
    stats = statistic(draws, axis=1)
    lo, hi = np.percentile(stats, [2.5, 97.5])
    return point, float(lo), float(hi)


__all__ = ["BOOTSTRAP", "CI_SEED", "bootstrap_ci", "iqm", "stratified_bootstrap"]
