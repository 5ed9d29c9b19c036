"""``youbot_fdi/fdi/decision.py``: the decision over a block of rows equals its one-row
recursions, written out by hand (the evidence, the torque levels and their operating point, the
shared-evidence and second-fault rules, the latch), whatever the block's length and the alarms
that change inside it; and its mechanisms against hand-derived closed forms (evidence per second
whatever the rate, the torque levels' operating point, evidence that drains, a second fault)."""
from dataclasses import replace
import math

from hypothesis import given, settings, strategies as st

import numpy as np
import pytest

from youbot_fdi.app.config import load_residual_data
from youbot_fdi.fdi.decision import DecisionMaker
from youbot_fdi.fdi.recursions import NEVER
from youbot_fdi.fdi.residuals import FAMILIES, ResidualBatch
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.model import load_model

from frames import torque_frame

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
    settings_ = FdiSettings(release_time=0.05, shared_window=0.5, shift_time_constant=0.3,
                            family_thresholds=(3.0,) * len(FAMILIES))
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
    threshold = s.family_thresholds[0]  # the same for every family (set so above)
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
    started; a wheel further than ``shift_operating_range`` of its own mean speed plus three
    ``speed_sigma``; a load factor further than the range of its mean),
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
        allowance = s.shift_operating_range * np.abs(mean[:4]) + 3 * s.speed_sigma
        away = count > 0 and ((np.abs(row[:4] - mean[:4]) > allowance).any()
                              or abs(row[4] - mean[4]) > s.shift_operating_range * mean[4])
        total, count = (row.copy(), 1) if away or count == 0 else (total + row, count + 1)
        expected.append(bool(away))
    np.testing.assert_array_equal(got, expected)
    np.testing.assert_array_equal(one_by_one, expected)


def first_alarm_time(model, rate, score, seconds=1.0):
    """When a constant torque score on one wheel first alarms [s from the first sample]."""
    settings = replace(FdiSettings(), breakaway_time=0.0)
    decision = DecisionMaker(model.wheel_names, settings, load_residual_data())
    for k in range(int(seconds * rate)):
        if any(e.level == 'ERROR' for e in decision.update(torque_frame(model, 10.0 + k / rate, score))):
            return k / rate
    return math.inf


def test_the_operating_point_of_the_torque_levels_changes_beyond_its_range(model):
    """Closed form, against the mean of the speeds since the operating point started: from 2 rad/s
    a wheel at 2.4 is the same point (0.4 within a quarter of its mean, 0.5, plus three
    speed_sigma, 0.03); at 2.7 (0.6 from the mean 2.1) another one, whose mean is the reference
    after; from rest a creep of 0.2 rad/s is another point (beyond three speed_sigma: a wheel
    leaving static friction), and 0.5 after it another again. A slow wheel beside fast ones is
    judged by its own speed: 0.4 -> 1.2 rad/s beside wheels at 8 leaves the point (0.8 > a
    quarter of 0.4 + 0.03), where a quarter of the fastest (2) would not. Row by row gives the
    same rows; a quantised reading jumping within three of its noise is no change."""
    s = FdiSettings()
    assert (s.shift_operating_range, s.stuck_speed, s.speed_sigma) == (0.25, 0.3, 0.01)
    speeds = np.full((8, 4), 2.0)
    speeds[2, 1] = 2.4  # 0.4 < 0.5 + 0.03: the same point
    speeds[4:, 1] = 2.7  # 0.6 from the mean 2.1 > 0.525 + 0.03: another point
    speeds[6:, 1] = 3.0  # 0.3 from 2.7: the same as row 4's
    speeds = np.vstack([speeds, np.zeros((2, 4)), [[0.2, 0.0, 0.0, 0.0]], [[0.5, 0.0, 0.0, 0.0]],
                        np.tile([8.0, 0.4, 8.0, 0.4], (3, 1)), [[8.0, 1.2, 8.0, 0.4]]])
    expected = np.zeros(len(speeds), dtype=bool)
    # 2.7; to rest; the creep from rest (0.2 > 0.03); 0.5 from it (0.3 > 0.05 + 0.03); the
    # drive; its slow wheel
    expected[[4, 8, 10, 11, 12, 15]] = True
    same_load = np.ones(len(speeds))
    batched = DecisionMaker(model.wheel_names, s, load_residual_data())
    np.testing.assert_array_equal(batched.operating_point_changes(speeds, same_load), expected)
    one_by_one = DecisionMaker(model.wheel_names, s, load_residual_data())
    rows = [bool(one_by_one.operating_point_changes(row[None], load[None])[0])
            for row, load in zip(speeds, same_load)]
    np.testing.assert_array_equal(rows, expected)
    # a Robotino's readings: two quantisation steps up now and then (0.6 > 0.45 + 0.03)
    quantised = np.tile(np.vstack([np.tile([1.4, -1.8, 0.4], (9, 1)), [[2.0, -1.8, 0.4]]]), (10, 1))
    noisy = DecisionMaker(model.wheel_names[:3], replace(s, speed_sigma=0.11), load_residual_data())
    assert not noisy.operating_point_changes(quantised, np.ones(len(quantised))).any()
    assert DecisionMaker(model.wheel_names[:3], s, load_residual_data()).operating_point_changes(
        quantised, np.ones(len(quantised))).any()  # the same jumps are moves for a reading without noise
    # the load factor the explained friction is scaled by is part of the point: from a mean of 2,
    # 2.4 is the same (0.4 < a quarter of 2); 2.7 is 0.6 from the mean 2.1 (> 0.525), another
    # point, the reference after
    steady, loads = np.full((6, 4), 2.0), np.array([2.0, 2.0, 2.4, 2.0, 2.7, 2.7])
    moved = np.zeros(6, dtype=bool)
    moved[4] = True
    batched = DecisionMaker(model.wheel_names, s, load_residual_data())
    np.testing.assert_array_equal(batched.operating_point_changes(steady, loads), moved)
    one_by_one = DecisionMaker(model.wheel_names, s, load_residual_data())
    np.testing.assert_array_equal(
        [bool(one_by_one.operating_point_changes(row[None], load[None])[0]) for row, load in zip(steady, loads)],
        moved)


@pytest.mark.parametrize('speed_after, alarms', [(2.0, True), (4.0, False)])
def test_a_torque_shift_is_evidence_only_at_the_operating_point_of_its_level(model, speed_after, alarms):
    """A wheel's torque residual at -0.5 bound for 4 s, then at +0.5 (inside the bound: the
    magnitude test adds nothing): at the same speeds that is a shift of one bound, an alarm
    within (shift_threshold / (1 - shift_drift)) intervals; at twice the speed it is another
    operating point, where the model's bias is another, and the level starts afresh (no alarm)."""
    s = replace(FdiSettings(), breakaway_time=0.0)
    first = shift_step_alarm(model, s, lambda stamp: torque_frame(model, stamp, -0.5),
                             lambda stamp: torque_frame(model, stamp, 0.5, speed=speed_after))
    assert first == (pytest.approx(one_bound_shift_alarm(s), abs=0.01 + 1e-9) if alarms else math.inf)


def shift_step_alarm(model, settings_, before, after, rate=100.0):
    """When [s after the step] the first ERROR comes in the second after 4 s of frames
    ``before(stamp)`` and then frames ``after(stamp)`` at ``rate`` [Hz] (inf: none); none before."""
    decision = DecisionMaker(model.wheel_names, settings_, load_residual_data())
    for k in range(int(4.0 * rate)):
        assert not decision.update(before(10.0 + k / rate))
    for k in range(int(4.0 * rate), int(5.0 * rate)):
        stamp = 10.0 + k / rate
        if any(e.level == 'ERROR' for e in decision.update(after(stamp))):
            return stamp - 14.0
    return math.inf


def one_bound_shift_alarm(settings_, rate=100.0):
    """When [s] a torque shift of one scale alarms at ``rate`` [Hz]: after shift_threshold / (1 -
    shift_drift) intervals."""
    return (math.ceil(settings_.shift_threshold / (1.0 - settings_.shift_drift)) - 1) / rate


def test_the_friction_change_within_an_operating_point_against_its_closed_form(model):
    """Closed form, 100 Hz: every wheel at 2 rad/s for 2 s, then wheel 0 at 1.6 (the same point:
    0.4 < a quarter of 2 plus three speed_sigma). The reference is the mean of the speeds before
    each row since the point started; the speed now is the reading averaged over
    load_time_constant, s_k = s_(k-1) + g (v_k - s_(k-1)), g = 1 - exp(-dt / 0.2), from the first
    reading; the change allowed is the friction level (0.5 N·m) times the larger of |s -
    reference| and |v - reference| less three speed_sigma (a step beyond the reading's noise at
    once), over the faster of s and the reference (at least stuck_speed). Row by row the same; a row without every reading
    (no part of the operating point) and a steady speed allow nothing."""
    s = FdiSettings()
    rate, rows, level = 100.0, 300, 0.5
    stamps = 10.0 + np.arange(rows) / rate
    speeds = np.full((rows, 4), 2.0)
    speeds[200:, 0] = 1.6
    speeds[250, 2] = np.nan  # a wheel without a reading: skipped by the operating point too
    friction = np.full((rows, 4), level)
    block = DecisionMaker(model.wheel_names, s, load_residual_data())
    assert not block.operating_point_changes(speeds, np.ones(rows)).any()
    got = block.friction_change(speeds, friction, stamps)
    gain = 1.0 - math.exp(-1.0 / rate / s.load_time_constant)
    expected = np.zeros((rows, 4))
    average = speeds[0, 0]
    for k in range(rows):
        complete = [j for j in range(k) if np.isfinite(speeds[j]).all()]
        reference = speeds[complete, 0].mean() if complete else speeds[k, 0]
        average = average + (gain if k else 1.0) * (speeds[k, 0] - average)
        departure = max(abs(average - reference), abs(speeds[k, 0] - reference) - 3 * s.speed_sigma)
        if np.isfinite(speeds[k]).all():  # a row without every reading is no part of the point
            expected[k, 0] = level * departure / max(abs(average), abs(reference), s.stuck_speed)
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-15)
    assert not got[250].any() and np.abs(got[:200]).max() < 1e-12  # steady: rounding only
    stepped = DecisionMaker(model.wheel_names, s, load_residual_data())
    one_by_one = []
    for k in range(rows):
        stepped.operating_point_changes(speeds[k:k + 1], np.ones(1))
        one_by_one.append(stepped.friction_change(speeds[k:k + 1], friction[k:k + 1], stamps[k:k + 1])[0])
    np.testing.assert_allclose(one_by_one, expected, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize('level, alarms', [(0.0, True), (5.0, False)])
def test_a_torque_shift_with_a_speed_change_allows_the_friction_an_unknown_split_moves(model, level, alarms):
    """A wheel's torque residual at -0.5 bound for 4 s at 2 rad/s, then at +0.5 while it slows to
    1.6 rad/s (the same operating point): without a friction level to move (0) that is a shift of
    one bound, an alarm within (shift_threshold / (1 - shift_drift)) intervals, as at a steady
    speed; with a friction level ten bounds large (5 N·m; the Robotino's level at x2 is five of its
    scales) an all-viscous friction would move by 5 x 0.4 / 2 = 1 bound at 1.6 rad/s, allowed at
    once less the reading's noise (5 x 0.37 / 2): the shift is within what the scale allows, no
    alarm in the second after."""
    s = replace(FdiSettings(), breakaway_time=0.0)
    levels = np.full(len(model.wheel_names), level)
    first = shift_step_alarm(
        model, s, lambda stamp: replace(torque_frame(model, stamp, -0.5), friction_level=levels),
        lambda stamp: replace(torque_frame(model, stamp, 0.5), velocity=np.array([1.6, 2.0, 2.0, 2.0]),
                              friction_level=levels))
    assert first == (pytest.approx(one_bound_shift_alarm(s), abs=0.01 + 1e-9) if alarms else math.inf)


@pytest.mark.parametrize('rate', [100.0, 250.0, 500.0])
def test_evidence_accumulates_per_second_whatever_the_rate(model, rate):
    """Closed form: a constant score z adds (z - drift) per evidence_interval; the alarm comes once
    threshold / (z - drift) intervals have passed: at 100, 250 or 500 Hz alike (the first sample
    counts a whole interval)."""
    s = FdiSettings()
    z = 2.0
    expected = (math.ceil(s.family_thresholds[0] / (z - s.evidence_drift)) - 1) * s.evidence_interval
    assert first_alarm_time(model, rate, z) == pytest.approx(expected, abs=1.0 / rate + 1e-9)


def test_a_slow_base_needs_as_many_samples_as_intervals(model):
    """At 20 Hz no sample counts for more than one interval: a single excess never alarms."""
    s = FdiSettings()
    z = 2.0
    samples = math.ceil(s.family_thresholds[0] / (z - s.evidence_drift))
    assert first_alarm_time(model, 20.0, z) == pytest.approx((samples - 1) / 20.0)


def test_evidence_that_drains_holds_no_new_alarm(model):
    """Two wheels' command residuals rise together (a shared change: no wheel fault) and fall
    back; the first drains at 1 a sample (score 0), the second at 0.5 (score 0.5), so after 7
    samples only the second is over the threshold, no longer shared. Evidence that drains tells of the
    shared excess, not of a fault now: no alarm. The second wheel's own excess after that (score
    2.5, evidence growing by 1.5 a sample from where it drained to) is one, on that wheel."""
    s = FdiSettings(family_thresholds=(3.0,) * len(FAMILIES))  # the numbers below are for 3
    decision = DecisionMaker(model.wheel_names, replace(s, breakaway_time=0.0), load_residual_data())
    n = len(model.wheel_names)

    def scores(first, second):
        f = torque_frame(model, 0.0, 0.0)
        values = dict(f.values, command=np.array([first, second, 0.0, 0.0]))
        return values

    plan = [(3.0, 3.0)] * 4 + [(0.0, 0.5)] * 8 + [(0.0, 2.5)] * 4
    events = []
    for k, (first, second) in enumerate(plan):
        f = replace(torque_frame(model, 10.0 + 0.01 * k, 0.0), values=scores(first, second))
        events += [(k, e.wheel) for e in decision.update(f) if e.level == 'ERROR']
    threshold = s.family_thresholds[FAMILIES.index('command')]
    assert 4 * 2.0 >= threshold  # both over the threshold together: shared
    # after 7 samples the first is under half the threshold (no longer up), the second still over
    assert 4 * 2.0 - 7 * 1.0 < 0.5 * threshold and 4 * 2.0 - 8 * 0.5 >= threshold
    assert n == 4 and events and events[0] == (12, model.wheel_names[1])


def test_beside_another_wheels_alarm_only_a_clear_excess_is_a_second_fault(model):
    """Wheel fl's command score 3 alarms at its second sample (evidence 2 a sample, threshold 3):
    it does not do what it was told (a runaway). While that alarm is set, fr's torque score 2.5
    (evidence 1.5 a sample, over the threshold at its second sample) is the excess a fault
    elsewhere gives the wheels it drags: no alarm. Its score 3.5 (at least
    ``second_fault_score``) is a second fault, found at once (the evidence it gathered is over
    the threshold and grows). Row by row and in one batch alike; without fl's alarm the same 2.5
    alarms at its second sample."""
    s = replace(FdiSettings(), breakaway_time=0.0, family_thresholds=(3.0,) * len(FAMILIES))
    assert s.second_fault_score == 3.0 and s.evidence_cap == 3.0
    plan = [(3.0, 0.0)] * 3 + [(3.0, 2.5)] * 10 + [(3.0, 3.5)] * 2

    def frames(plan):
        for k, (first, second) in enumerate(plan):
            f = torque_frame(model, 10.0 + 0.01 * k, 0.0)
            yield replace(f, values=dict(f.values, command=np.array([first, 0.0, 0.0, 0.0]),
                                         torque=np.array([0.0, second, 0.0, 0.0])))

    def alarms(decision, plan):
        return [(k, e.wheel) for k, f in enumerate(frames(plan)) for e in decision.update(f)
                if e.level == 'ERROR']

    fl, fr = model.wheel_names[:2]
    assert alarms(DecisionMaker(model.wheel_names, s, load_residual_data()), plan) == [(1, fl), (13, fr)]
    batched = DecisionMaker(model.wheel_names, s, load_residual_data())
    events = batched.update_batch(ResidualBatch.of_frames(list(frames(plan))))
    assert [(round((e.stamp - 10.0) / 0.01), e.wheel) for e in events if e.level == 'ERROR'] == [
        (1, fl), (13, fr)]
    alone = [(0.0, second) for _, second in plan]
    assert alarms(DecisionMaker(model.wheel_names, s, load_residual_data()), alone)[0] == (4, fr)
