"""Friction trends across a robot's recordings: which wheel is wearing before it fails.

Per robot and wheel, the identified viscous friction against the recordings' start times: a
least-squares line, its slope relative to the mean friction [1/day] and the slope's p-value (the
t-test of ``scipy.stats.linregress``). A wheel is flagged when its friction rises faster than
``trend_rate`` per day and the rise is significant at ``trend_significance``.
"""
from dataclasses import dataclass
import math

SECONDS_PER_DAY = 86400.0


@dataclass(frozen=True)
class Trend:
    """The friction trend of one wheel of one robot."""

    robot: str
    wheel: str
    recordings: int
    mean: float  # [N·m·s/rad]
    rate: float  # relative slope [1/day]
    p_value: float
    flagged: bool


def friction_trends(rows, settings):
    """Trends (robot, wheel order) from ``recordings.csv`` rows (dicts with robot, start, wheels,
    friction); robots with fewer than ``trend_min_recordings`` usable recordings are left out."""
    import numpy as np
    from scipy.stats import linregress
    trends = []
    for robot in sorted({r['robot'] for r in rows}):
        mine = [r for r in rows if r['robot'] == robot and r.get('wheels') and math.isfinite(r['start'])]
        if not mine:
            continue
        for w, wheel in enumerate(mine[0]['wheels']):
            points = [(r['start'], r['friction'][w]) for r in mine
                      if len(r['friction']) > w and math.isfinite(r['friction'][w])]
            if len(points) < settings.trend_min_recordings:
                continue
            t, f = (np.array(v, dtype=float) for v in zip(*points))
            days = (t - t.min()) / SECONDS_PER_DAY
            mean = float(np.mean(f))
            if np.ptp(days) == 0.0 or mean <= 0.0:
                continue
            fit = linregress(days, f)
            rate = float(fit.slope / mean)
            p_value = float(fit.pvalue) if math.isfinite(fit.pvalue) else 1.0
            trends.append(Trend(robot, wheel, len(points), mean, rate, p_value,
                                rate > settings.trend_rate and p_value < settings.trend_significance))
    return trends
