"""``youbot_fdi/fdi/decision.py``: the decision over a block of rows equals its one-row
recursions, written out by hand (the evidence, the torque levels and their operating point, the
shared-evidence and second-fault rules, the latch), whatever the block's length and the alarms
that change inside it."""
from hypothesis import given, settings, strategies as st

import numpy as np

from youbot_fdi.app.config import load_residual_data
from youbot_fdi.fdi.decision import DecisionMaker
from youbot_fdi.fdi.recursions import NEVER
from youbot_fdi.fdi.residuals import FAMILIES
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.model import load_model
import pytest

FAST_EXCEPT = ()  # `make check`: every test here (the unit tests of the core, under a minute)


@pytest.fixture(scope='module')
def model():
    return load_model('youbot')


@settings(max_examples=80, deadline=None)
@given(rows=st.integers(1, 200), seed=st.integers(0, 2**32 - 1))
def test_batched_alarms_equal_the_sequential_evidence_latch(model, rows, seed):
    """Evidence (the magnitude CUSUM, and the torque shift CUSUMs against a level that holds still
    while the wheel's torque alarm is set), the shared-evidence rule, alarms raised only by evidence
    that grows, and release hysteresis over a
    block, from any state it was left in, equal the one-row recursions; so do the rows in which the
    base breaks away from rest (no torque evidence, the level starts afresh) and those in which
    the wheels leave the level's operating point (the level starts afresh). Blocks longer than
    the parts an alarm change is judged again in (``REJUDGED_ROWS``)."""
    settings_ = FdiSettings(release_time=0.05, shared_window=0.5, shift_time_constant=0.3)
    rng = np.random.default_rng(seed)
    shape = (len(FAMILIES), 4)
    batched = DecisionMaker(model.wheel_names, settings_, load_residual_data())
    batched._evidence = rng.random(shape) * 4.0
    batched._shift = rng.random((2, 4)) * 8.0
    batched._level.value, batched._level.weight = rng.normal(size=4) * 0.1, rng.choice([0.0, 0.5, 1.0], 4)
    batched._typical_bound.value = np.log(rng.uniform(0.05, 0.2, size=4))
    batched._typical_bound.weight = rng.choice([0.0, 0.5, 1.0], size=4)
    batched._last_stamp = rng.choice([np.nan, -0.1])
    batched._below = rng.integers(0, 6, size=shape) * settings_.evidence_interval
    batched.alarm = rng.random(shape) < 0.5
    batched._rise = np.where(batched._evidence >= 1.5, -rng.random(shape), batched._rise)
    evidence, below, alarm = batched._evidence.copy(), batched._below.copy(), batched.alarm.copy()
    shift, level, weight = batched._shift.copy(), batched._level.value.copy(), batched._level.weight.copy()
    typical, typical_weight = batched._typical_bound.value.copy(), batched._typical_bound.weight.copy()
    last, rise = batched._last_stamp, batched._rise.copy()
    batched._fault_stamp = np.where(rng.random(4) < 0.5, -rng.random(4) * 2.0, NEVER)
    fault_stamp = batched._fault_stamp.copy()
    z = rng.random((rows, *shape)) * rng.uniform(0.5, 4.0)
    torque = rng.normal(size=(rows, 4)) * rng.uniform(0.05, 0.5) + (np.arange(rows) > rows // 2)[:, None] * 0.3
    torque[rng.random((rows, 4)) < 0.05] = np.nan  # no effort recorded
    bound = rng.uniform(0.05, 0.2, size=(rows, 4)) * np.where(rng.random((rows, 4)) < 0.1, 20.0, 1.0)
    excited = rng.random((rows, 4)) < 0.7
    stamps = np.cumsum(rng.uniform(0.002, 0.4, rows))  # some closer than evidence_interval
    breaking = rng.random(rows) < 0.15
    moved = rng.random(rows) < 0.1
    got = batched._alarms(z, excited, stamps, torque, bound, bound, breaking, moved)  # bound as scale
    s = settings_
    threshold = s.family_thresholds[0]  # the same for every family by default
    level_share = 0.5 * threshold
    scale = threshold / s.shift_threshold
    judged_before = evidence.copy()
    judged_before[0] = np.maximum(judged_before[0], shift.max(axis=0) * scale)
    for k in range(rows):
        was_up = np.maximum(evidence, np.vstack([np.maximum(shift.max(axis=0) * scale, evidence[0]),
                                                 evidence[1:]])) >= level_share
        # beside another wheel's fault: its torque, command or encoder alarm set after the row
        # before, or set less than heal_time ago
        faulty = alarm[[0, 2, 3]].any(axis=0) | (stamps[k] - fault_stamp < s.heal_time)
        elsewhere = [faulty[np.arange(4) != w].any() for w in range(4)]
        # the row's evidence weight: the time it stands for, at most one interval
        row_weight = 1.0 if np.isnan(last) else min(1.0, (stamps[k] - last) / s.evidence_interval)
        # the torque shift, against the level before this row
        present = np.isfinite(torque[k])
        # breaking away from rest and leaving the operating point start the level afresh
        fresh = breaking[k] or moved[k]
        judged_now = present & ~fresh
        x = np.where(judged_now & (weight >= 0.5), (np.nan_to_num(torque[k]) - level) / bound[k], 0.0)
        gain = 0.0 if np.isnan(last) else 1.0 - np.exp(-(stamps[k] - last) / s.shift_time_constant)
        # the bound's usual size (a geometric average), and the sample's precision against it
        precision = np.minimum(1.0, (np.exp(typical) / bound[k]) ** 2)
        if_steady = np.full(4, not fresh) | alarm[0]
        weight = np.where(if_steady, weight, 0.0)
        typical_gain = gain * present
        typical_weight = typical_weight + typical_gain * (1.0 - typical_weight)
        typical = np.where(typical_weight > 0, typical + np.divide(
            typical_gain, typical_weight, out=np.zeros(4), where=typical_weight > 0)
            * (np.log(np.where(present, bound[k], 1.0)) - typical), typical)
        gain = gain * precision * (judged_now & ~alarm[0])
        weight = weight + gain * (1.0 - weight)
        inside = np.clip(np.nan_to_num(torque[k]), -bound[k], bound[k])
        level = np.where(weight > 0, level + np.divide(gain, weight, out=np.zeros(4), where=weight > 0)
                         * (inside - level), level)
        last = stamps[k]
        x = np.clip(x, -s.evidence_cap, s.evidence_cap)
        shift = np.clip(shift + row_weight * (np.stack([x, -x]) - s.shift_drift), 0.0, 2.0 * s.shift_threshold)
        scores = z[k].copy()
        scores[0] = 0.0 if breaking[k] else scores[0]  # no torque evidence while breaking away
        evidence = np.maximum(0.0, evidence + row_weight * (np.minimum(scores, s.evidence_cap) - s.evidence_drift))
        judged = evidence.copy()
        judged[0] = np.maximum(judged[0], shift.max(axis=0) * scale)
        up = judged >= level_share
        rise = np.where(up & ~was_up, stamps[k], rise)
        over = judged >= threshold
        for family in (0, 2):  # torque, command: not while half the wheels rose together, nor
            for w in range(4):  # a modest score while half the wheels have evidence
                together = sum(up[family, v] and abs(rise[family, v] - rise[family, w]) <= 0.5
                               for v in range(4))
                if together >= 2 or (np.count_nonzero(up[family]) >= 2 and scores[family, w] < 3.0):
                    over[family, w] = False
                if elsewhere[w] and scores[family, w] < 3.0:  # a fault elsewhere drags this wheel
                    over[family, w] = False
        below = np.where(over, 0.0, np.where(excited[k], below + row_weight * s.evidence_interval, below))
        # raised where the evidence is over and grows; held while it is over
        alarm = np.where(over & (judged > judged_before), True,
                         np.where(below >= s.release_time - 1e-9, False, alarm))
        judged_before = judged
        fault_stamp = np.where(alarm[[0, 2, 3]].any(axis=0), stamps[k], fault_stamp)
        np.testing.assert_array_equal(got[k], alarm)
    np.testing.assert_allclose(batched._evidence, evidence, atol=1e-9)
    np.testing.assert_allclose(batched._shift, shift, atol=1e-9)
    np.testing.assert_allclose(batched._level.value, level, atol=1e-9)
    np.testing.assert_allclose(batched._typical_bound.value, typical, atol=1e-9)
    np.testing.assert_allclose(batched._below, below, atol=1e-9)
    np.testing.assert_array_equal(batched._fault_stamp, fault_stamp)


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 40), seed=st.integers(0, 2**32 - 1))
def test_breaking_away_from_rest_is_the_same_over_a_block_and_row_by_row(model, rows, seed):
    """The rows in which the base breaks away from rest (some wheel turns, less than
    breakaway_time after a row in which every wheel stood), over a block from any earlier rest,
    equal those found one row at a time and the definition."""
    settings_ = FdiSettings()
    rng = np.random.default_rng(seed)
    speed = rng.choice([0.0, 0.1, 0.5, 3.0], size=(rows, 4), p=[0.4, 0.2, 0.2, 0.2])
    stamps = 5.0 + np.cumsum(rng.uniform(0.01, 0.1, rows))
    rest = rng.choice([-1e300, 4.9, 4.99])  # never, or a little before the block
    block, stepped = (DecisionMaker(model.wheel_names, settings_, load_residual_data()) for _ in range(2))
    block._rest_stamp = stepped._rest_stamp = rest
    got = block._breaking_away(speed, stamps)
    one_by_one = np.concatenate([stepped._breaking_away(speed[k:k + 1], stamps[k:k + 1])
                                 for k in range(rows)])
    expected = []
    for k in range(rows):
        resting = bool((np.abs(speed[k]) <= settings_.stuck_speed).all())
        rest = stamps[k] if resting else rest
        expected.append(not resting and stamps[k] - rest < settings_.breakaway_time)
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(one_by_one, expected)
    assert block._rest_stamp == stepped._rest_stamp == rest




@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 700), seed=st.integers(0, 2**32 - 1))
def test_the_operating_point_is_the_same_over_a_block_and_row_by_row(model, rows, seed):
    """The rows that leave the operating point (the mean of the speeds and load factors since it
    started; a wheel further than ``shift_operating_range`` of the fastest mean speed, or
    ``stuck_speed``, plus three ``speed_sigma``; a load factor further than the range of its mean),
    by its loop, over blocks long enough for the search's block to grow and shrink (drives that
    change their point every few rows and ones that hold it for hundreds); a row without every
    reading is skipped."""
    settings_ = FdiSettings()
    rng = np.random.default_rng(seed)
    hold = rng.choice([3, 30, 300])  # rows a point typically lasts
    jumps = rng.random(rows) < 1.0 / hold
    speeds = np.cumsum(jumps[:, None] * rng.normal(scale=3.0, size=(rows, 4)), axis=0)
    speeds += rng.normal(scale=0.02, size=(rows, 4))
    loads = 1.0 + np.cumsum(jumps * rng.normal(scale=0.4, size=rows)) ** 2
    speeds[rng.random(rows) < 0.03, rng.integers(0, 4)] = np.nan
    block = DecisionMaker(model.wheel_names, settings_, load_residual_data())
    got = block.operating_point_changes(speeds, loads)
    stepped = DecisionMaker(model.wheel_names, settings_, load_residual_data())
    one_by_one = [bool(stepped.operating_point_changes(speeds[k:k + 1], loads[k:k + 1])[0])
                  for k in range(rows)]
    s, total, count, expected = settings_, np.zeros(5), 0, []
    for row in np.column_stack([speeds, loads]):
        if not np.isfinite(row).all():
            expected.append(False)
            continue
        mean = total / max(count, 1)
        allowance = max(s.shift_operating_range * np.abs(mean[:4]).max(), s.stuck_speed) + 3 * s.speed_sigma
        away = count > 0 and (np.abs(row[:4] - mean[:4]).max() > allowance
                              or abs(row[4] - mean[4]) > s.shift_operating_range * mean[4])
        total, count = (row.copy(), 1) if away or count == 0 else (total + row, count + 1)
        expected.append(bool(away))
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(one_by_one, expected)
