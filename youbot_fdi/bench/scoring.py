"""Scoring a fault benchmark case from its fault events, and the printed table of a suite.

Shared by every suite of ``youbot-fdi bench --faults``: one rule for what counts as detected,
isolated, named right, how late, and what is a false alarm.
"""
from dataclasses import dataclass
import math

import numpy as np

from youbot_fdi.faults import Level, LOAD_CHANGE, UNSEEN_OPERATING_POINT
from youbot_fdi.fdi.lifecycle import closest_events, component

ERROR = Level.ERROR
#: The type named for an episode is its last ERROR on that wheel within this time of the first [s]
#: (a type may be refined once the classification window is full).
NAMING_WINDOW = 0.55
#: The one-sided confidence of the printed upper bound on a suite's false-alarm rate [-]: a
#: count of alarms in some hours is one draw of a Poisson count, and "0 in 393 s" says far less
#: than "0 in 20 h" (at most 27 per hour against 0.15).
RATE_CONFIDENCE = 0.95


@dataclass(frozen=True)
class Case:
    """One recording of a suite and what was injected into it."""

    name: str
    path: str  # the rosbag2 recording
    duration: float  # [s]
    fault: object = None  # the injected fault (suite's own name), or None
    wheel: object = None  # joint name
    onset: float = math.nan  # header stamp from which the fault is in the data [s]
    expected: object = None  # the fault type the contract would name, or None (any type)
    start: float = 0.0  # header stamp of the recording's first sample [s]
    injected: float = math.nan  # when the fault was injected, if before it shows (runaway) [s]


def opening(events):
    """The ERROR events of ``events`` (in stamp order) that open an episode: a component's first
    ERROR, or its first after an OK. A type refined within an episode (``fdi/lifecycle.py``) is
    a second ERROR of the same alarm, not another one."""
    opened, previous = [], {}
    for event in events:
        key = component(event)
        if event.level == ERROR and previous.get(key) != ERROR:
            opened.append(event)
        previous[key] = event.level
    return opened


def score(case, events):
    """A result dict for ``case`` from its fault events (FaultEvent list). False alarms are the
    alarms of its fault-free driving (before a fault began, the time ``fault_free_seconds`` they
    are a rate of), counted as episodes (:func:`opening`, ``false_alarms``) and as ERROR events
    (``false_alarm_events``: with the types refined within them). Alarms on other wheels after a
    fault began are that fault's isolation, not driving without one: ``other_wheels`` (a wheel
    that does not follow the kinematics drags the others; isolation is judged by the first)."""
    alarms = [e for e in events if e.level == ERROR]
    episodes = {id(e) for e in opening(events)}
    faulty = case.fault is not None
    begins = case.onset if math.isnan(case.injected) else min(case.injected, case.onset)
    early = [e for e in alarms if not faulty or e.stamp < begins]
    late = [e for e in alarms if faulty and e.stamp >= begins]
    first = late[0] if late else None
    named = None
    if first is not None:
        episode = [e for e in late if e.wheel == first.wheel and e.stamp - first.stamp <= NAMING_WINDOW]
        named = episode[-1].fault
    fault_free = begins - case.start if faulty else case.duration
    return {'case': case.name, 'fault': case.fault, 'wheel': case.wheel,
            'fault_free_seconds': fault_free,
            'false_alarms': sum(id(e) in episodes for e in early),
            'false_alarm_events': len(early),
            'other_wheels': len({e.wheel for e in late} - {case.wheel}),
            'false_alarm_faults': sorted({f'{e.wheel}:{e.fault}' for e in early}),
            'detected': first is not None,
            'isolated': first is not None and first.wheel == case.wheel,
            'named': first is not None and (case.expected is None or named == case.expected),
            'named_as': named,
            'delay': (max(0.0, first.stamp - case.onset) if first is not None
                      and not math.isnan(case.onset) else math.nan),  # onset NaN: never visible
            'warnings': sum(e.level == Level.WARN and e.fault == LOAD_CHANGE for e in events),
            'unseen_warnings': sum(e.level == Level.WARN and e.fault == UNSEEN_OPERATING_POINT
                                   for e in events),
            'closest_events': closest_events(events)}


def rate_upper_bound(alarms, hours, confidence=RATE_CONFIDENCE):
    """The exact one-sided upper confidence bound [per hour] of a Poisson rate of which
    ``alarms`` events were counted in ``hours`` [h]: the rate at which ``alarms`` or fewer come
    with probability ``1 - confidence``, ``gammaincinv(alarms + 1, confidence) / hours`` (for no
    alarm, ``-ln(1 - confidence) / hours``); inf without hours."""
    from scipy.special import gammaincinv
    if alarms < 0 or not 0.0 < confidence < 1.0:
        msg = f'rate_upper_bound needs alarms >= 0 and 0 < confidence < 1, got {alarms}, {confidence}'
        raise ValueError(msg)
    return float(gammaincinv(alarms + 1, confidence)) / hours if hours > 0 else math.inf


def rate_text(alarms, hours):
    """' = r per hour (at most u per hour, 95 % one-sided)' for ``alarms`` in ``hours`` [h], ''
    without hours."""
    if not hours:
        return ''
    bound = rate_upper_bound(alarms, hours)
    digits = '.2g' if bound < 100.0 else '.0f'  # two significant digits, no exponent
    return (f' = {alarms / hours:{digits}} per hour (at most {bound:{digits}} per hour, '
            f'{RATE_CONFIDENCE:.0%} one-sided)')


def summarise(title, results):
    """The printed table of one suite: per fault, then totals (false alarms per hour)."""
    faulty = [r for r in results if r['fault']]
    hours = sum(r['fault_free_seconds'] for r in results) / 3600.0
    false_alarms = sum(r['false_alarms'] for r in results)
    lines = [title, f'  {"fault":<18}{"cases":>6}{"detected":>10}{"isolated":>10}{"named":>8}'
                    f'{"median delay":>14}{"p90 delay":>11}']
    for fault in sorted({r['fault'] for r in faulty}):
        rows = [r for r in faulty if r['fault'] == fault]
        lines.append('  ' + _row(fault, rows))
    lines.append('  ' + _row('all faults', faulty))
    # every judged run counts (a recording judged by several folds or plants' runs that share a
    # name count once each); the names are listed once
    alarmed = sum(1 for r in results if r['false_alarms'])
    with_alarms = sorted({r['case'] for r in results if r['false_alarms']})
    events = sum(r['false_alarm_events'] for r in results)
    lines.append(f'  false alarms        {false_alarms} in {hours * 3600:.0f} s fault-free'
                 + rate_text(false_alarms, hours)
                 + (f' ({events} ERROR events with the types refined)' if events != false_alarms
                    else '')
                 + f'; runs with one: {alarmed} of {len(results)}'
                 + (f' ({len(with_alarms)} recordings)' if len(with_alarms) != alarmed else ''))
    if with_alarms:
        lines.append('    ' + ', '.join(with_alarms[:12]) + (' ...' if len(with_alarms) > 12 else ''))
    others = [r['other_wheels'] for r in faulty]
    if any(others):
        lines.append(f'  alarms on another wheel after a fault began (its isolation, not fault-free '
                     f'driving): {sum(others)} in {sum(1 for o in others if o)} of {len(faulty)} '
                     f'fault runs')
    lines.append(f'  load-condition warnings (WARN, not alarms): {sum(r["warnings"] for r in results)}; '
                 f'operating point not seen in calibration: '
                 f'{sum(r.get("unseen_warnings", 0) for r in results)}')
    lines.append('  ' + dwell_line(results))
    return '\n'.join(lines)


def dwell_line(results, dwell=None):
    """The printed check of the event lifecycle's dwell over ``results``: the closest two events
    of one component in any run, and the runs where two came closer than ``dwell`` [s] (default:
    the configured one)."""
    if dwell is None:
        from youbot_fdi.fdi.settings import FdiSettings
        from youbot_fdi.settings import load_settings
        dwell = load_settings(FdiSettings, 'fdi').dwell
    gaps = [r.get('closest_events', math.inf) for r in results]
    closest = min(gaps, default=math.inf)
    under = sum(gap < dwell - 1e-9 for gap in gaps)
    shown = 'no component evented twice' if math.isinf(closest) else f'{closest:.2f} s'
    return (f'closest two events of one component: {shown} (dwell {dwell:g} s); '
            f'runs with two closer: {under} of {len(results)}')


def delay_quantiles(results):
    """(median, p90) [s] of the detection delays of the results detected and isolated; both NaN
    when there are none."""
    delays = np.array([r['delay'] for r in results if r['detected'] and r['isolated']])
    if not len(delays):
        return math.nan, math.nan
    return float(np.median(delays)), float(np.percentile(delays, 90))


def _row(label, rows):
    median, p90 = delay_quantiles(rows)
    return (f'{label:<18}{len(rows):>6}{sum(r["detected"] for r in rows):>10}'
            f'{sum(r["isolated"] for r in rows):>10}{sum(r["named"] for r in rows):>8}'
            f'{median * 1000:>12.0f}ms{p90 * 1000:>9.0f}ms')


def replay_scored(case, params):
    """Replay ``case`` with each variant's parameter file ({variant: path}); {variant: result
    dict}, a fault-free run's with its residual spread (``spread``, held back from calibration:
    the ablation pools it)."""
    from youbot_fdi.app.config import build_pipeline
    from youbot_fdi.app.replay import replay_recording
    out = {}
    for variant, file in params.items():
        replayed = replay_recording(build_pipeline(file)[1], case.path)
        out[variant] = {**score(case, replayed.events),
                        'spread': replayed.spread if case.fault is None else None}
    return out


def pooled_spread(results):
    """{family: RMS} pooled over the results' held-back spreads (fault-free runs), or {}."""
    from youbot_fdi.fdi.residuals import ResidualSpread
    spreads = [r['spread'] for r in results if r.get('spread') is not None]
    pooled = ResidualSpread()
    for spread in spreads:
        pooled.merge(spread)
    return pooled.rms() if spreads else {}


def ablation(rows):
    """The physics-only vs learned table (issue 12): one line per (suite, variant, results,
    spread), spread = {variant: {family: RMS on the calibration recording}} or None; the held-back
    spread is pooled from the fault-free results (:func:`pooled_spread`)."""
    lines = ['Ablation: physics-only vs learned corrections (same recordings, same bounds)',
             f'  {"":<22}{"torque RMS":^21}{"observer":>10}',
             f'  {"suite":<13}{"variant":<9}{"calib.":>9}{"held back":>12}{"held back":>10}'
             f'{"detected":>10}{"isolated":>10}{"median":>9}{"p90":>8}{"false alarms/h":>16}']
    for suite, variant, results, spread in rows:
        faulty = [r for r in results if r['fault'] and r.get('observable', True)]
        median, p90 = delay_quantiles(faulty)
        hours = sum(r['fault_free_seconds'] for r in results) / 3600.0
        alarms = sum(r['false_alarms'] for r in results)
        rms = (spread or {}).get(variant) or {}
        held = pooled_spread(results)
        lines.append(f'  {suite:<13}{variant:<9}{rms.get("torque", math.nan):>9.4g}'
                     f'{held.get("torque", math.nan):>12.4g}{held.get("observer", math.nan):>10.4g}'
                     f'{sum(r["detected"] for r in faulty):>6}/{len(faulty):<3}'
                     f'{sum(r["isolated"] for r in faulty):>6}/{len(faulty):<3}'
                     f'{median * 1000:>7.0f}ms{p90 * 1000:>6.0f}ms'
                     f'{(alarms / hours if hours else math.nan):>16.1f}')
    lines.append('  (RMS [N·m, rad/s] over the wheels: "calib." on the calibration recording, '
                 '"held back" pooled over the fault-free recordings; delays of faults detected '
                 'and isolated)')
    return '\n'.join(lines)
