"""95% intervals for success rates: over seeds (Student's t on the per-seed means) and over
episodes (Wilson's score interval on the pooled successes). Plain NumPy; no SciPy at run time.

    lo, hi = seed_interval([0.8, 0.9])           # t with 1 degree of freedom: wide, as it should be
    lo, hi = wilson(successes=90, n=100)
    lo, hi = newcombe(56, 70, 48, 80)            # p1 - p2 over two samples of episodes
    lo, hi = paired_interval([0.04, 0.06, 0.16]) # a difference measured on each seed
    cuts_by_outcome(success, pruned)             # legs cut per episode, apart for successes and failures
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

# Student's t, two-sided 95% (the 0.975 quantile) for 1..30 degrees of freedom; beyond, the Cornish-Fisher
# expansion around the normal quantile. tests/test_compare.py checks both against scipy.stats.t.ppf.
T975 = (12.7062, 4.3027, 3.1824, 2.7764, 2.5706, 2.4469, 2.3646, 2.3060, 2.2622, 2.2281, 2.2010, 2.1788, 2.1604,
        2.1448, 2.1314, 2.1199, 2.1098, 2.1009, 2.0930, 2.0860, 2.0796, 2.0739, 2.0687, 2.0639, 2.0595, 2.0555,
        2.0518, 2.0484, 2.0452, 2.0423)
Z975 = 1.959964


def t975(df: int) -> float:
    """The 0.975 quantile of Student's t with ``df`` >= 1 degrees of freedom."""
    if df < 1:
        raise ValueError(f'a t interval needs at least 1 degree of freedom (2 values); got {df}')
    if df <= len(T975):
        return T975[df - 1]
    z = Z975
    return z + (z ** 3 + z) / (4 * df) + (5 * z ** 5 + 16 * z ** 3 + 3 * z) / (96 * df ** 2)


def seed_interval(values: Sequence[float]) -> tuple[float, float]:
    """95% t interval of the mean of ``values`` (one per seed), clipped to [0, 1]. With one value
    there is no spread to estimate: ``(nan, nan)``."""
    lo, hi = paired_interval(values)
    return (lo, hi) if math.isnan(lo) else (max(0.0, lo), min(1.0, hi))


def wilson(successes: float, n: int, z: float = Z975) -> tuple[float, float]:
    """Wilson's 95% score interval of a binomial rate with ``successes`` out of ``n`` trials."""
    if n < 1 or not 0 <= successes <= n:
        raise ValueError(f'wilson: need 0 <= successes <= n and n >= 1; got {successes} of {n}')
    p = successes / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return max(0.0, centre - half), min(1.0, centre + half)


def newcombe(k1: int, n1: int, k2: int, n2: int) -> tuple[float, float]:
    """95% interval of ``k1 / n1 - k2 / n2`` from the two Wilson intervals (Newcombe's method 10), for
    two rates over separate episodes (unpaired)."""
    p1, p2 = k1 / n1, k2 / n2
    l1, u1 = wilson(k1, n1)
    l2, u2 = wilson(k2, n2)
    d = p1 - p2
    return d - math.sqrt((p1 - l1) ** 2 + (u2 - p2) ** 2), d + math.sqrt((u1 - p1) ** 2 + (p2 - l2) ** 2)


def paired_interval(differences: Sequence[float]) -> tuple[float, float]:
    """95% t interval of the mean of per-seed ``differences`` (not clipped: a difference may be
    negative). With one value: ``(nan, nan)``."""
    v = [float(x) for x in differences]
    if not v or any(math.isnan(x) for x in v):
        raise ValueError(f'a t interval needs finite values; got {differences!r}')
    if len(v) < 2:
        return math.nan, math.nan
    mean = sum(v) / len(v)
    half = t975(len(v) - 1) * math.sqrt(sum((x - mean) ** 2 for x in v) / (len(v) - 1)) / math.sqrt(len(v))
    return mean - half, mean + half


def cuts_by_outcome(success, pruned) -> dict:
    """Legs cut per episode, over all episodes and apart for those that succeeded and those that failed.

    Args:
        success: ``bool [E]`` per episode.
        pruned: ``int [E]`` legs cut in the episode.
    Returns:
        ``{'all', 'succeeded', 'failed'}``: mean cuts per episode of each group (NaN for an empty group),
        with ``'n'`` and ``'n_succeeded'``.
    """
    success, pruned = np.asarray(success, bool).ravel(), np.asarray(pruned, float).ravel()
    if success.shape != pruned.shape:
        raise ValueError(f'success {success.shape} and pruned {pruned.shape} must have one entry per episode')

    def mean(x):
        return float(x.mean()) if x.size else float('nan')

    return dict(all=mean(pruned), succeeded=mean(pruned[success]), failed=mean(pruned[~success]),
                n=int(success.size), n_succeeded=int(success.sum()))
