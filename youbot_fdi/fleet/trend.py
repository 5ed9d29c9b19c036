"""Friction trends across a robot's recordings: which wheel is wearing before it fails.

Per robot and wheel, the identified viscous friction against the recordings' start times, each
with the standard deviation ``identify`` states: a line by weighted least squares (weights
1 / sd²), its slope relative to the mean friction [1/day] and the slope's p-value. The slope's
standard error is the one the stated deviations give, or the one the scatter about the line
gives where that is larger (the deviations count noise, not a model that misses: the Birge
ratio). A wheel is flagged when its friction rises faster than ``trend_rate`` per day, the rise
is significant at ``trend_significance``, and the line's ends lie further apart than their
intervals (± INTERVAL_SDS deviations of the first and the last recording): a change is called
only where the intervals separate. Without stated deviations (rows of an older fleet run) the
line is ordinary least squares and the last condition is left out.
"""
from dataclasses import dataclass
import math

SECONDS_PER_DAY = 86400.0
INTERVAL_SDS = 2.0  # an interval is the value ± this many standard deviations (95 % if honest)


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
    trends = []
    for robot in sorted({r['robot'] for r in rows}):
        mine = [r for r in rows if r['robot'] == robot and r.get('wheels') and math.isfinite(r['start'])]
        if not mine:
            continue
        for w, wheel in enumerate(mine[0]['wheels']):
            points = [(r['start'], r['friction'][w], _deviation(r, w)) for r in mine
                      if len(r['friction']) > w and math.isfinite(r['friction'][w])]
            if len(points) < settings.trend_min_recordings:
                continue
            t, f, sd = (np.array(v, dtype=float) for v in zip(*points))
            days = (t - t.min()) / SECONDS_PER_DAY
            mean = float(np.mean(f))
            if np.ptp(days) == 0.0 or mean <= 0.0:
                continue
            slope, p_value, separated = _weighted_line(days, f, sd)
            rate = float(slope / mean)
            trends.append(Trend(robot, wheel, len(points), mean, rate, p_value,
                                rate > settings.trend_rate and p_value < settings.trend_significance
                                and separated))
    return trends


def _deviation(row, wheel):
    """The stated standard deviation of ``row``'s friction of ``wheel`` (NaN where none)."""
    spread = row.get('friction_sd') or []
    return float(spread[wheel]) if len(spread) > wheel else math.nan


def _weighted_line(days, friction, sd):
    """(slope [N·m·s/rad per day], its one-sided p-value for a rise, whether the line's ends
    lie further apart than the first and last recordings' intervals) of ``friction`` against
    ``days`` (module docstring)."""
    import numpy as np
    from scipy.stats import t as student
    stated = bool(np.all(np.isfinite(sd)) and np.all(sd > 0.0))
    weight = 1.0 / sd ** 2 if stated else np.ones_like(friction)
    design = np.column_stack([np.ones_like(days), days])
    normal = design.T @ (weight[:, None] * design)
    coefficients = np.linalg.solve(normal, design.T @ (weight * friction))
    residual = friction - design @ coefficients
    dof = len(days) - 2
    scatter = float(np.sum(weight * residual ** 2)) / dof if dof > 0 else math.inf
    # Known deviations: the scatter only widens the error (Birge); unknown: it is the error.
    scale = max(1.0, scatter) if stated else scatter
    error = math.sqrt(np.linalg.inv(normal)[1, 1] * scale) if math.isfinite(scale) else math.inf
    slope = float(coefficients[1])
    p_value = float(student.sf(slope / error, max(dof, 1))) if error > 0.0 else (0.0 if slope > 0 else 1.0)
    rise = slope * float(np.ptp(days))
    separated = (not stated) or rise > INTERVAL_SDS * (sd[np.argmin(days)] + sd[np.argmax(days)])
    return slope, p_value, bool(separated)
