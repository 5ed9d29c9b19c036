"""Cycle timing a node can show on /diagnostics: period and lateness, p50 / p99 / max.

Plain Python (no numpy on the hot path): one :meth:`CycleTiming.tick` per cycle costs a few
list operations; the percentiles are computed only when diagnostics are published.
"""
from dataclasses import dataclass
import math

#: Cycles kept for the percentiles (about 10 s at 100 Hz): recent behaviour, bounded memory.
DEFAULT_WINDOW = 1024


@dataclass(frozen=True)
class TimingSummary:
    """Period and lateness over the recent cycles [s]; the maxima and counts since the start."""

    cycles: int
    period_p50: float
    period_p99: float
    period_max: float
    lateness_p50: float
    lateness_p99: float
    lateness_max: float
    late_cycles: int  # cycles later than ``late_after`` since the start

    def values(self, prefix=''):
        """Diagnostic key-values: periods and lateness in ms, counts as integers."""
        ms = {'period_p50': self.period_p50, 'period_p99': self.period_p99,
              'period_max': self.period_max, 'lateness_p50': self.lateness_p50,
              'lateness_p99': self.lateness_p99, 'lateness_max': self.lateness_max}
        out = {f'{prefix}{key}_ms': f'{1000.0 * value:.2f}' for key, value in ms.items()}
        out[f'{prefix}cycles'] = str(self.cycles)
        out[f'{prefix}late_cycles'] = str(self.late_cycles)
        return out


def _percentile(ordered, share):
    """The ``share`` (0..1) quantile of the sorted list ``ordered`` (nearest rank); NaN if empty."""
    if not ordered:
        return math.nan
    return ordered[min(len(ordered) - 1, max(0, math.ceil(share * len(ordered)) - 1))]


class CycleTiming:
    """Period between ticks and lateness of each tick, for a loop meant to run every
    ``nominal_period`` seconds (a timer, or a stream of samples).

    Lateness is how much later than one nominal period after the previous tick a tick came
    (0 when on time or early), or, for a stream of stamped samples, how long after its stamp a
    sample arrived (``tick(now, due=stamp)``). A tick later than ``late_after`` [s] counts as a
    late cycle (for the driver shim: the modules' controller timeout, past which they stop their
    motors).
    """

    def __init__(self, nominal_period, late_after=math.inf, window=DEFAULT_WINDOW):
        if not nominal_period > 0.0:
            msg = f'nominal_period must be > 0 s, got {nominal_period!r}'
            raise ValueError(msg)
        self.nominal_period = nominal_period
        self.late_after = late_after
        self.window = int(window)
        self._periods = []
        self._lateness = []
        self._next = 0  # ring-buffer position once the window is full
        self._last = None
        self.cycles = 0
        self.late_cycles = 0
        self.period_max = 0.0
        self.lateness_max = 0.0

    def tick(self, now, due=None):
        """One cycle started (or one sample arrived) at ``now`` [s], due at ``due`` [s] (default:
        one nominal period after the last tick); returns its lateness [s]."""
        last, self._last = self._last, now
        self.cycles += 1
        if last is None:
            return 0.0
        period = now - last
        lateness = max(0.0, period - self.nominal_period if due is None else now - due)
        if len(self._periods) < self.window:
            self._periods.append(period)
            self._lateness.append(lateness)
        else:
            self._periods[self._next] = period
            self._lateness[self._next] = lateness
            self._next = (self._next + 1) % self.window
        self.period_max = max(self.period_max, period)
        self.lateness_max = max(self.lateness_max, lateness)
        if lateness > self.late_after:
            self.late_cycles += 1
        return lateness

    def summary(self):
        """A :class:`TimingSummary` of the recent window (maxima since the start)."""
        periods, lateness = sorted(self._periods), sorted(self._lateness)
        return TimingSummary(self.cycles, _percentile(periods, 0.5), _percentile(periods, 0.99),
                             self.period_max, _percentile(lateness, 0.5),
                             _percentile(lateness, 0.99), self.lateness_max, self.late_cycles)


def parse_cores(text):
    """CPU indices from ``'1'`` or ``'0,1'`` (empty: no affinity); ValueError naming the text."""
    text = str(text).strip()
    if not text:
        return ()
    try:
        cores = tuple(sorted({int(part) for part in text.split(',') if part.strip()}))
    except ValueError:
        msg = f'cpu_cores must be comma-separated CPU indices like "1" or "0,1", got {text!r}'
        raise ValueError(msg) from None
    if any(core < 0 for core in cores):
        msg = f'cpu_cores must be >= 0, got {text!r}'
        raise ValueError(msg)
    return cores


def apply_scheduling(priority=0, cores=()):
    """Real-time priority (SCHED_FIFO ``priority`` 1..99; 0 leaves the default scheduler) and CPU
    affinity (``cores``; empty: any) for the calling process and the threads it starts after
    this call (Linux threads inherit both). Where the OS does not permit it (no CAP_SYS_NICE,
    no such core, not Linux) nothing changes. Returns one line per request saying what was done
    or why not, for the node's log."""
    import os
    lines = []
    if cores:
        try:
            os.sched_setaffinity(0, set(cores))
            lines.append(f'CPU affinity: cores {",".join(map(str, cores))}')
        except (AttributeError, OSError, ValueError) as err:
            lines.append(f'CPU affinity {cores} not applied ({err}); running on any core')
    if priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))
            lines.append(f'real-time scheduling: SCHED_FIFO priority {int(priority)}')
        except (AttributeError, OSError, ValueError) as err:
            lines.append(f'real-time priority {int(priority)} not applied ({err}); needs CAP_SYS_NICE '
                         'or an rtprio limit (/etc/security/limits.conf); default scheduler')
    return lines
