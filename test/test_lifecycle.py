"""The event lifecycle (``fdi/lifecycle.py``, issue 32): an alarm is an episode, confirmed once,
held, healed with hysteresis; no two events of one component within the dwell."""
import math

import numpy as np
import pytest

from youbot_fdi.fdi.decision import FaultEvent
from youbot_fdi.fdi.lifecycle import EventLifecycle, LifecycleSettings, closest_events

pytestmark = pytest.mark.fast  # `make check`: the unit tests of the core, under a minute

STEP = 0.01  # [s] rows


def raw(stamp, level, wheel='wheel_joint_fl', fault='stuck'):
    return FaultEvent(round(stamp, 6), level, wheel, fault, ('torque_fl',) if level != 'OK' else ())


def flapping(period_rows=4, until=2.0):
    """A raw alarm that comes and goes every ``period_rows`` rows (20-50 ms flaps) until ``until``
    [s], then stays OK: rows' stamps and the raw events."""
    stamps = np.round(np.arange(0.0, until + 3.0, STEP), 6)
    events = []
    for k, stamp in enumerate(stamps):
        if stamp >= until:
            if events and events[-1].level != 'OK':
                events.append(raw(stamp, 'OK'))
            break
        if k % period_rows == 0:
            events.append(raw(stamp, 'ERROR' if (k // period_rows) % 2 == 0 else 'OK'))
    return stamps, events


def test_a_flapping_alarm_is_one_episode_with_a_count():
    settings = LifecycleSettings(confirm_time=0.0, heal_time=0.5, dwell=0.2)
    stamps, events = flapping()
    published = EventLifecycle(settings).feed(events, stamps)
    assert [e.level for e in published] == ['ERROR', 'OK']
    assert published[0].stamp == 0.0
    last_ok = events[-1]
    assert last_ok.level == 'OK' and published[1].stamp == pytest.approx(last_ok.stamp + settings.heal_time)
    returns = sum(1 for e in events if e.level == 'ERROR') - 1
    assert f'came back {returns} time(s)' in published[1].detail


def test_confirmation_skips_a_blip_and_times_a_standing_alarm():
    settings = LifecycleSettings(confirm_time=0.05, heal_time=0.3, dwell=0.0)
    stamps = np.round(np.arange(0.0, 2.0, STEP), 6)
    events = [raw(0.10, 'ERROR'), raw(0.12, 'OK'),  # 20 ms: never confirmed
              raw(0.50, 'ERROR'), raw(1.00, 'OK')]
    published = EventLifecycle(settings).feed(events, stamps)
    assert [(e.level, e.stamp) for e in published] == [('ERROR', 0.55), ('OK', 1.3)]


def test_a_type_refined_within_the_episode_waits_for_the_dwell():
    settings = LifecycleSettings(confirm_time=0.0, heal_time=0.5, dwell=0.3)
    stamps = np.round(np.arange(0.0, 2.0, STEP), 6)
    events = [raw(0.1, 'ERROR', fault='unknown'), raw(0.15, 'ERROR', fault='friction')]
    published = EventLifecycle(settings).feed(events, stamps)
    assert [(e.fault, e.stamp) for e in published] == [('unknown', 0.1), ('friction', 0.4)]


def test_an_episodes_type_is_refined_once_among_the_classified_types():
    """torque_loss, refined to friction (published after the dwell); the raw alarm drops and
    returns as torque_loss, then friction, then torque_loss again, all within the episode: held
    as friction, each return counted. A different kind of fault (stuck) is news and published;
    after healing, a new episode names its type afresh."""
    settings = LifecycleSettings(confirm_time=0.0, heal_time=0.5, dwell=0.3)
    stamps = np.round(np.arange(0.0, 6.0, STEP), 6)
    events = [raw(0.1, 'ERROR', fault='torque_loss'), raw(0.2, 'ERROR', fault='friction'),
              raw(0.8, 'OK'), raw(0.9, 'ERROR', fault='torque_loss'),
              raw(1.0, 'OK'), raw(1.1, 'ERROR', fault='friction'),
              raw(1.2, 'OK'), raw(1.3, 'ERROR', fault='torque_loss'), raw(1.6, 'ERROR', fault='stuck'),
              raw(2.0, 'OK'), raw(3.0, 'ERROR', fault='torque_loss')]
    published = EventLifecycle(settings).feed(events, stamps)
    assert [(e.level, e.fault, e.stamp) for e in published] == [
        ('ERROR', 'torque_loss', 0.1), ('ERROR', 'friction', 0.4), ('ERROR', 'stuck', 1.6),
        ('OK', 'stuck', 2.5), ('ERROR', 'torque_loss', 3.0)]
    assert 'came back 3 time(s)' in published[3].detail


@pytest.mark.parametrize('dwell', [0.05, 0.3])
def test_no_two_events_of_a_component_closer_than_the_dwell(dwell):
    settings = LifecycleSettings(confirm_time=0.0, heal_time=0.02, dwell=dwell)
    stamps, events = flapping(period_rows=3)
    other = [raw(e.stamp, e.level, wheel='wheel_joint_br') for e in events]
    merged = sorted(events + other, key=lambda e: e.stamp)
    published = EventLifecycle(settings).feed(merged, stamps)
    for wheel in ('wheel_joint_fl', 'wheel_joint_br'):
        times = [e.stamp for e in published if e.wheel == wheel]
        assert len(times) >= 2 and min(np.diff(times)) >= dwell - 1e-9


def test_a_block_and_row_by_row_publish_the_same_events():
    settings = LifecycleSettings(confirm_time=0.03, heal_time=0.4, dwell=0.1)
    stamps, events = flapping(period_rows=5)
    events += [raw(0.7, 'WARN', wheel=None, fault='load_change'), raw(1.5, 'OK', wheel=None,
                                                                    fault='load_change')]
    events.sort(key=lambda e: e.stamp)
    block = EventLifecycle(settings).feed(events, stamps)
    one = EventLifecycle(settings)
    rows = [e for stamp in stamps for e in one.feed([x for x in events if x.stamp == stamp], [stamp])]
    assert [e.to_dict() for e in rows] == [e.to_dict() for e in block]
    assert {e.fault for e in block} == {'stuck', 'load_change'}  # separate components


def test_reset_ends_what_is_shown_at_once():
    lifecycle = EventLifecycle(LifecycleSettings(confirm_time=0.0, heal_time=1.0, dwell=0.5))
    assert [e.level for e in lifecycle.feed([raw(0.0, 'ERROR')], [0.0])] == ['ERROR']
    events = lifecycle.reset(0.01, 'repaired')
    assert [(e.level, e.wheel, e.detail) for e in events] == [('OK', 'wheel_joint_fl', 'repaired')]
    assert lifecycle.shown(('wheel_joint_fl', 'fault')) == ('OK', '')


def test_the_closest_events_of_one_component_are_measured_per_component():
    events = [raw(0.0, 'ERROR'), raw(0.1, 'ERROR', wheel='wheel_joint_br'),  # other component
              raw(0.7, 'OK'), raw(1.0, 'ERROR', wheel='wheel_joint_fl', fault='friction'),
              raw(1.05, 'WARN', wheel=None, fault='load_change')]  # a condition: its own channel
    assert closest_events(events) == pytest.approx(0.3)  # fl: 0.0, 0.7, 1.0
    assert closest_events(events[:2]) == math.inf
    from youbot_fdi.bench.scoring import dwell_line
    line = dwell_line([{'closest_events': 0.3}, {'closest_events': math.inf}], dwell=0.5)
    assert '0.30 s (dwell 0.5 s)' in line and 'runs with two closer: 1 of 2' in line
