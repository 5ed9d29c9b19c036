"""The false-alarm rate of an evidence CUSUM, from nominal scores held back from the fit.

The decision accumulates each residual's evidence as a CUSUM, ``g = max(0, g + x)``, with
increments ``x = w (min(z, cap) - drift)`` (``fdi/decision.py``). On nominal data the increments
drift down; an alarm needs an excursion to reach the threshold h. For a random walk whose
increments X have a negative mean, the probability that an excursion ever rises by h is at most
``exp(-theta h)`` (Lundberg's inequality), theta the positive root of ``log E[exp(theta X)] = 0``.
Residuals are correlated over a few samples, so X are the increments' sums over blocks as long
as that correlation (then nearly independent), and every block may start an excursion: the
alarm rate is at most ``blocks per hour x exp(-theta h)``. A union bound, so the stated rate is
an upper bound in the conditions the scores came from: it says nothing of floors or speeds
calibration did not see (the bounds' extrapolation does, ``fdi/residuals.py``).

A wheel's silence (its module not answering while the others do) is counted in samples, not
accumulated: :class:`SilenceEstimate` states the rate of runs of k missed answers from the share of
answers the calibration recording lacked (an upper confidence bound), misses taken as independent
between samples; no run shorter than the longest calibration saw is ever a fault.

Plain numpy (and scipy.special); ``identify`` feeds it held-back scores and prints the rate at
each threshold.
"""
from __future__ import annotations

from dataclasses import dataclass
import math

import numpy as np
import scipy.special

from youbot_fdi.fdi.recursions import run_lengths

#: A score's autocorrelation below this ends the block (1/e: the correlation time).
BLOCK_CORRELATION = math.exp(-1.0)
MAX_BLOCK = 200  # [samples] the longest block considered
SECONDS_PER_HOUR = 3600.0
#: The one-sided confidence of the upper bound on the chance of a missed answer (Clopper-Pearson).
MISS_CONFIDENCE = 0.95


@dataclass(frozen=True)
class RateEstimate:
    """A CUSUM's alarm rate: ``exponent`` theta [1/evidence], independent ``blocks_per_hour``
    per stream (wheel), ``streams`` (wheels) judged at once; inf exponent: the block sums never
    rise (no alarm at any threshold); 0: they drift up (alarms at every threshold)."""

    exponent: float
    blocks_per_hour: float
    streams: int

    def rate(self, threshold: float) -> float:
        """Alarms per hour of driving at ``threshold`` (all streams), an upper bound."""
        if math.isinf(self.exponent):
            return 0.0
        return self.streams * self.blocks_per_hour * math.exp(-self.exponent * threshold)

    def threshold(self, rate: float) -> float:
        """The lowest threshold whose :meth:`rate` is at most ``rate`` [per hour] (inf: none)."""
        if math.isinf(self.exponent):
            return 0.0
        if self.exponent <= 0.0:
            return math.inf
        return max(0.0, math.log(self.streams * self.blocks_per_hour / rate) / self.exponent)


def correlation_length(scores: np.ndarray) -> int:
    """Samples (>= 1) over which scores (N, streams) stay correlated: the first lag whose
    autocorrelation, pooled over the streams, falls below :data:`BLOCK_CORRELATION`."""
    centred = scores - np.nanmean(scores, axis=0)
    centred = np.where(np.isfinite(centred), centred, 0.0)
    variance = float(np.sum(centred * centred))
    if variance <= 0.0:
        return 1
    for lag in range(1, min(MAX_BLOCK, len(scores) // 4)):
        if np.sum(centred[lag:] * centred[:-lag]) / variance < BLOCK_CORRELATION:
            return lag
    return min(MAX_BLOCK, max(1, len(scores) // 4))


def lundberg_exponent(sums: np.ndarray) -> float:
    """The positive root theta of ``log mean(exp(theta X)) = 0`` for block sums X (M,); inf when
    no sum is positive, 0 when their mean is not negative."""
    x = np.asarray(sums, dtype=float)
    x = x[np.isfinite(x)]
    if not len(x) or x.max() <= 0.0:
        return math.inf
    if x.mean() >= 0.0:
        return 0.0
    top = x.max()

    def excess(theta):  # log mean exp(theta x), computed stably
        return theta * top + math.log(np.mean(np.exp(theta * (x - top))))

    low, high = 0.0, 1.0
    while excess(high) < 0.0:
        low, high = high, 2.0 * high
    for _ in range(80):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if excess(middle) < 0.0 else (low, middle)
    return 0.5 * (low + high)


def estimate(increments: np.ndarray, scores: np.ndarray, interval: float) -> RateEstimate:
    """The :class:`RateEstimate` of a CUSUM whose increments (N, streams) come from ``scores``
    (N, streams) sampled every ``interval`` [s] (NaN rows: no data, left out)."""
    increments = np.asarray(increments, dtype=float)
    block = correlation_length(np.asarray(scores, dtype=float))
    rows = (len(increments) // block) * block
    if rows == 0:
        return RateEstimate(0.0, SECONDS_PER_HOUR / max(interval, 1e-9), increments.shape[1])
    sums = np.nansum(increments[:rows].reshape(-1, block, increments.shape[1]), axis=1).ravel()
    return RateEstimate(lundberg_exponent(sums), SECONDS_PER_HOUR / (block * interval),
                        increments.shape[1])


@dataclass(frozen=True)
class SilenceEstimate:
    """Runs of missed answers of one wheel's module: ``miss_chance`` [-] per sample (an upper
    bound at :data:`MISS_CONFIDENCE` from calibration), ``longest`` [samples] the longest run
    calibration saw, ``samples_per_hour``, ``streams`` (wheels). A run of k starts at a sample
    with chance ``miss_chance ** k`` if misses are independent; one the length of a run
    calibration saw is never taken for a fault, independent or not."""

    miss_chance: float
    longest: int
    samples_per_hour: float
    streams: int

    def rate(self, threshold: float) -> float:
        """Silences per hour reaching ``threshold`` samples in a row (all wheels), an upper
        bound; inf at a threshold calibration saw reached."""
        if threshold <= self.longest:
            return math.inf
        return self.streams * self.samples_per_hour * self.miss_chance ** threshold

    def threshold(self, rate: float) -> float:
        """The fewest samples in a row whose :meth:`rate` is at most ``rate`` [per hour]."""
        if self.miss_chance <= 0.0:
            return float(self.longest + 1)
        if self.miss_chance >= 1.0:
            return math.inf
        needed = math.log(rate / (self.streams * self.samples_per_hour)) / math.log(self.miss_chance)
        return float(max(self.longest + 1, math.ceil(needed - 1e-9)))


def longest_run(missed: np.ndarray) -> int:
    """The longest run of True down the rows of ``missed`` (N, streams), over every stream."""
    missed = np.asarray(missed, dtype=bool)
    if missed.ndim != 2:
        raise ValueError(f'missed must be (N, streams), got shape {missed.shape}')
    if not missed.size:
        return 0
    return int(run_lengths(missed, np.zeros(missed.shape[1], dtype=int)).max())


def silence_estimate(answered: np.ndarray, interval: float) -> SilenceEstimate:
    """The :class:`SilenceEstimate` of a recording whose rows (N, wheels) say which wheels
    answered, sampled every ``interval`` [s]: the wheel that missed most sets the chance."""
    answered = np.asarray(answered, dtype=bool)
    if answered.ndim != 2 or not len(answered):
        raise ValueError(f'answered must be (N >= 1, wheels), got shape {answered.shape}')
    if not interval > 0.0:
        raise ValueError(f'interval must be positive, got {interval} s')
    rows = len(answered)
    missed = int(np.max(np.count_nonzero(~answered, axis=0)))
    # Clopper-Pearson: the chance under which ``missed`` or fewer misses in ``rows`` samples had
    # probability 1 - MISS_CONFIDENCE
    chance = (1.0 if missed >= rows
              else float(scipy.special.betaincinv(missed + 1, rows - missed, MISS_CONFIDENCE)))
    return SilenceEstimate(chance, longest_run(~answered), SECONDS_PER_HOUR / interval,
                           answered.shape[1])
