"""Mechanisms of issue 32 that keep the FDI quiet where calibration did not reach, each checked
against a hand-derived closed form: evidence per second whatever the rate, bounds that widen
beyond the calibrated range, a command path that does not predict a current calibration never
saw, a frozen-reading test that needs a turning wheel, and a load factor without a clamp."""
from dataclasses import replace
import math

import numpy as np
import pytest

from youbot_fdi.fdi.decision import DecisionMaker
from youbot_fdi.fdi.learned import mask_wheels
from youbot_fdi.app.config import load_residual_data
from youbot_fdi.fdi.residuals import (BOUND_TERMS, FAMILIES, FROZEN_MIN_TICKS, SPEED_NOISE_SIGMAS,
                                      PRIOR_SETTINGS, ResidualBatch, ResidualEvaluator, ResidualFrame,
                                      bound_weights)
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.model import load_model
from youbot_fdi.model.firmware import slowest_time_constant


@pytest.fixture(scope='module')
def model():
    return load_model('youbot')


def frame(model, stamp, torque_score, speed=2.0):
    n = len(model.wheel_names)
    values = {f: np.zeros(n) for f in FAMILIES}
    values['torque'] = np.array([torque_score, 0.0, 0.0, 0.0])
    return ResidualFrame(stamp=stamp, values=values, bounds={f: np.ones(n) for f in FAMILIES},
                         velocity=np.full(n, speed), torque=np.full(n, 0.5), velocity_mode=True,
                         command=np.full(n, 2.0), frozen=np.zeros(n, dtype=int),
                         effort_frozen=np.zeros(n, dtype=int), position_frozen=np.zeros(n, dtype=int),
                         silent=np.zeros(n))


def first_alarm_time(model, rate, score, seconds=1.0):
    """When a constant torque score on one wheel first alarms [s from the first sample]."""
    settings = replace(FdiSettings(), breakaway_time=0.0)
    decision = DecisionMaker(model.wheel_names, settings, load_residual_data())
    for k in range(int(seconds * rate)):
        if any(e.level == 'ERROR' for e in decision.update(frame(model, 10.0 + k / rate, score))):
            return k / rate
    return math.inf


def test_the_operating_point_of_the_torque_levels_changes_beyond_its_range(model):
    """Closed form, against the mean of the speeds since the operating point started: from 2 rad/s
    a wheel at 2.4 is the same point (0.4 within a quarter of the fastest mean, 0.5, plus three
    speed_sigma, 0.03); at 2.7 (0.6 from the mean 2.1) another one, whose mean is the reference
    after; near standstill a change under stuck_speed is none. Row by row gives the same rows;
    a quantised reading jumping within three of its noise is no change."""
    s = FdiSettings()
    assert (s.shift_operating_range, s.stuck_speed, s.speed_sigma) == (0.25, 0.3, 0.01)
    speeds = np.full((8, 4), 2.0)
    speeds[2, 1] = 2.4  # 0.4 < 0.5 + 0.03: the same point
    speeds[4:, 1] = 2.7  # 0.6 from the mean 2.1 > 0.525 + 0.03: another point
    speeds[6:, 1] = 3.0  # 0.3 from 2.7: the same as row 4's
    speeds = np.vstack([speeds, np.zeros((2, 4)), [[0.2, 0.0, 0.0, 0.0]], [[0.5, 0.0, 0.0, 0.0]]])
    expected = np.zeros(len(speeds), dtype=bool)
    expected[[4, 8, 11]] = True  # 2.7; to rest; 0.5 - 0.07 > stuck_speed + 0.03 at rest (not 0.2)
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
    decision = DecisionMaker(model.wheel_names, s, load_residual_data())
    rate = 100.0
    for k in range(int(4.0 * rate)):
        assert not decision.update(frame(model, 10.0 + k / rate, -0.5))
    first = math.inf
    for k in range(int(4.0 * rate), int(5.0 * rate)):
        stamp = 10.0 + k / rate
        if any(e.level == 'ERROR' for e in decision.update(frame(model, stamp, 0.5, speed_after))):
            first = min(first, stamp - 14.0)
    if alarms:
        intervals = math.ceil(s.shift_threshold / (1.0 - s.shift_drift)) - 1
        assert first == pytest.approx(intervals / rate, abs=1.0 / rate + 1e-9)
    else:
        assert first == math.inf


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


def test_bounds_beyond_the_calibrated_range_widen_with_the_prior(model):
    """Inside the range the learned weights; a feature's excess beyond it is weighed with the
    larger of the learned and the default weight."""
    learned = dict(zip(BOUND_TERMS['torque'], (0.05, 0.0, 0.1, 0.2)))  # calibration saw no inertia
    settings = replace(FdiSettings(), torque_feature_range=(math.inf, 0.5, 2.0, 1.0), **learned)
    evaluator = ResidualEvaluator(model, settings)
    features = np.array([[1.0, 2.5, 1.0, 1.5]])  # inertial torque 5x the range, friction 1.5x
    prior = bound_weights(PRIOR_SETTINGS, 'torque')
    w = np.array(list(learned.values()))
    inside = np.array([1.0, 0.5, 1.0, 1.0])
    excess = features[0] - inside
    expected = inside @ w + excess @ np.maximum(w, prior)
    assert evaluator.bound('torque', features)[0] == pytest.approx(expected)
    assert expected > features[0] @ w  # wider than the learned bound extrapolated
    within = np.array([[1.0, 0.4, 1.5, 0.9]])
    assert evaluator.bound('torque', within)[0] == pytest.approx(within[0] @ w)
    beyond = evaluator.beyond_calibration({'torque': np.stack([features, within], axis=0)})
    assert beyond.tolist() == [[True], [False]]


def test_the_command_bound_remembers_an_extrapolated_transient_as_the_loop_does(model):
    """A row whose predicted acceleration is X beyond what calibration covered widens the command
    bound by w X (w: the larger of the learned and the default weight); the rows after it, inside
    the range again, keep w X exp(-(t - t_0) / tau), tau the loop's slowest time constant (the
    time a guessed start takes to fade), the same row by row; nothing while settling, nothing
    from before a restart."""
    learned = dict(zip(BOUND_TERMS['command'], (0.02, 0.01, 0.05, 0.004)))
    settings = replace(FdiSettings(), command_feature_range=(math.inf, 10.0, 3.0, 5.0), **learned)
    evaluator = ResidualEvaluator(model, settings)
    tau = slowest_time_constant(model.dynamics, model.drive.torque_per_amp, model.firmware)
    weight = max(learned['command_delay'], bound_weights(PRIOR_SETTINGS, 'command')[3])
    rows, dt, excess = 12, 0.01, 20.0  # [rad/s²] beyond the range, on wheel 1 only
    stamp = 100.0 + dt * np.arange(rows)
    features = np.tile([1.0, 2.0, 0.5, 1.0], (rows, 4, 1))
    features[0, 1, 3] = 5.0 + excess
    mode, calm = np.ones(rows, dtype=bool), np.zeros((rows, 4), dtype=bool)
    fresh = np.zeros(rows, dtype=bool)
    added = evaluator._remembered_extrapolation(features, mode, calm, stamp, fresh)
    expected = np.zeros((rows, 4))
    expected[1:, 1] = weight * excess * np.exp(-(stamp[1:] - stamp[0]) / tau)
    np.testing.assert_allclose(added, expected, rtol=1e-9, atol=1e-12)
    assert evaluator.bound('command', features[:1])[0, 1] == pytest.approx(
        features[0, 1] @ np.array(list(learned.values())) - 20.0 * learned['command_delay']
        + weight * excess)  # the row itself: its own excess, in the bound already
    one_by_one = ResidualEvaluator(model, settings)
    by_row = np.concatenate([one_by_one._remembered_extrapolation(
        features[k:k + 1], mode[k:k + 1], calm[k:k + 1], stamp[k:k + 1], fresh[k:k + 1])
        for k in range(rows)])
    np.testing.assert_array_equal(by_row, added)
    settling = evaluator._remembered_extrapolation(features, mode, ~calm, stamp + 1.0, fresh)
    assert np.all(settling == 0.0)
    restart = fresh.copy()
    restart[3] = True
    after = ResidualEvaluator(model, settings)._remembered_extrapolation(features, mode, calm, stamp,
                                                                        restart)
    np.testing.assert_allclose(after[:3], expected[:3], rtol=1e-9, atol=1e-12)
    assert np.all(after[3:] == 0.0)
    current_mode = mode.copy()
    current_mode[2:] = False  # an effort bound [N·m] takes nothing of the speed's memory
    mixed = ResidualEvaluator(model, settings)._remembered_extrapolation(features, current_mode, calm,
                                                                        stamp, fresh)
    np.testing.assert_allclose(mixed[:2], expected[:2], rtol=1e-9, atol=1e-12)
    assert np.all(mixed[2:] == 0.0)


def test_the_command_path_takes_the_measured_state_at_a_current_calibration_never_saw(model):
    """A saturating drive's current limit is unknown beyond what calibration measured: there the
    prediction is the measured speed (no evidence), and it predicts again from that state once
    the current is back within range."""
    from youbot_fdi.fdi.observer import CALIBRATED_SHARE, ModelObserver
    from youbot_fdi.samples import CommandSample, JointSample
    limit = 1.0  # [N·m] calibration's largest torque
    observer = ModelObserver(model, replace(FdiSettings(), calibrated_effort=limit))
    observer.command(CommandSample(0.0, 'velocity', np.full(4, 5.0)))
    speeds = np.array([1.0, 1.5, 2.0, 2.5])
    observer.update(JointSample(0.01, np.zeros(4), speeds, np.zeros(4)))
    high = np.full(4, CALIBRATED_SHARE * limit + 0.01)
    prediction = observer.update(JointSample(0.02, np.zeros(4), speeds + 0.1, high * model.kinematics.drive_signs))
    held = model.kinematics.drive_signs * (speeds + 0.1)  # the sample, kinematic convention
    np.testing.assert_allclose(prediction.from_commands, held)
    assert prediction.outside_calibration == 0.0  # within the margin: held, not yet a WARN
    assert prediction.resynced  # it started again from a guessed state
    low = observer.update(JointSample(0.03, np.zeros(4), speeds + 0.2, np.full(4, 0.1)))
    assert low.resynced  # and the row after (its integral is the loop's again)
    later = observer.update(JointSample(0.04, np.zeros(4), speeds + 0.3, np.full(4, 0.1)))
    assert np.all(np.abs(later.from_commands - held) > 1e-6) and not later.resynced  # predicting


@pytest.mark.parametrize('integral_gain', [None, 3.0])
def test_the_command_path_settles_after_it_took_the_measured_state(model, integral_gain):
    """Where a wheel's current reached what calibration never saw, the command path took the
    measured state, and that wheel's integral is a guess (its loop may have wound up): its
    command residual is not judged for ``startup_time`` after the last such row, as after a
    start, or for three of the loop's slowest time constants if that is longer (a weak integral
    gain forgets a wrong guess slowly), and is again after it. The other wheels' integrals,
    implied by currents within the loop's range, are the loop's: they are judged throughout."""
    from youbot_fdi.fdi.residuals import SETTLE_TIME_CONSTANTS, ResidualGenerator
    from youbot_fdi.model import slowest_time_constant
    from youbot_fdi.model.profile import PlatformModel
    from youbot_fdi.samples import CommandSample, JointSample
    if integral_gain is not None:
        model = PlatformModel(replace(model.profile, firmware=replace(model.firmware,
                                                                      velocity_ki=integral_gain)))
    settings = replace(FdiSettings(), calibrated_effort=1.0, startup_time=0.2)
    settle = max(settings.startup_time, SETTLE_TIME_CONSTANTS * slowest_time_constant(
        model.dynamics, model.drive.torque_per_amp, model.firmware))
    assert (settle > 0.5) == (integral_gain is not None)  # the weak gain: longer than startup_time
    generator = ResidualGenerator(model, settings)
    generator.command(CommandSample(0.0, 'velocity', np.full(4, 5.0)))
    signs = model.kinematics.drive_signs
    judged = {}
    rows = int(round((0.31 + settle) / 0.01)) + 10
    for k in range(1, rows):
        stamp = 0.01 * k
        effort = np.full(4, 0.1)
        if k == 30:
            effort[2] = 2.0  # one sample of wheel bl at twice calibration's largest torque
        frame = generator.update(JointSample(stamp, np.zeros(4), signs * 1.0, signs * effort))
        if frame is not None:
            judged[round(stamp, 2)] = frame.values['command'] != 0.0
    assert not judged[0.3].any() and not judged[0.31].any()
    assert judged[0.29].all() or integral_gain is not None  # a slow loop still settles from its start
    # settling: after the row after the jump (0.31 s), for bl alone
    for j in range(1, int(settle / 0.01) - 1):
        now = judged[round(0.31 + 0.01 * j, 2)]
        assert not now[2]
        assert now[[0, 1, 3]].all() or 0.01 * (31 + j) < 0.01 + settle  # the start (0.01 s) settling
    after = round(0.31 + 0.01 * (int(settle / 0.01) + 2), 2)
    assert judged[after].all()


def test_a_noisy_speed_reading_at_rest_is_not_a_turning_wheel(model):
    """The frozen-position test counts a wheel as turning only where its speed less
    SPEED_NOISE_SIGMAS x speed_sigma moves the encoder by FROZEN_MIN_TICKS in the interval."""
    sigma = 0.05  # [rad/s]
    evaluator = ResidualEvaluator(model, replace(FdiSettings(), speed_sigma=sigma))
    step = 0.002  # 500 Hz
    needed = FROZEN_MIN_TICKS * evaluator.position_quantum / step + SPEED_NOISE_SIGMAS * sigma
    speeds = np.array([[0.5 * needed, 0.99 * needed, 1.01 * needed, 3 * needed]])
    moving = evaluator._moving(speeds, np.zeros((1, 4)), np.array([[False]]), step)
    assert moving.tolist() == [[False, False, True, True]]


def test_the_load_factor_follows_a_platform_change_of_any_size(model):
    """No clamp: every wheel needing about three times its friction is a factor of about 3 (the
    median); one wheel alone cannot move it; most wheels changing alike while one does not (a
    floor that triples rolling friction and leaves a sliding wheel's) is most wheels' change."""
    from youbot_fdi.fdi.observer import ModelObserver
    observer = ModelObserver(model, FdiSettings())
    friction = np.full(4, 0.2)

    def factor(ratios, previous=1.0, voting=(True,) * 4):
        votes = np.where(voting, friction, 0.0)
        row = np.concatenate([np.array(ratios) * votes, votes])[None]
        return float(observer._load_factor(row, previous)[0])

    assert factor([3.2, 3.0, 3.4, 3.1]) == pytest.approx(3.15)
    assert factor([5.0, 1.0, 1.0, 1.0]) == pytest.approx(1.0)
    assert factor([3.3, 1.0, 3.3, 3.2]) == pytest.approx(3.25)


def test_two_voters_move_the_load_factor_as_far_as_both_agree(model):
    """Where only two wheels vote (the others stand), the factor before stands in for the rest:
    the median of the two and it. Both needing more moves it by the smaller change; one wheel alone
    (a fault) does not move it; one voter holds it."""
    from youbot_fdi.fdi.observer import ModelObserver
    observer = ModelObserver(model, FdiSettings())
    friction = np.array([0.2, 0.2, 0.0, 0.0])  # two wheels stand: no friction level, no vote

    def factor(ratios, previous):
        return float(observer._load_factor(
            np.concatenate([np.array(ratios + [0.0, 0.0]) * friction, friction])[None], previous)[0])

    assert factor([2.1, 1.8], 1.0) == pytest.approx(1.8)  # both: the smaller change
    assert factor([0.6, 0.7], 1.0) == pytest.approx(0.7)
    assert factor([5.0, 1.05], 1.0) == pytest.approx(1.05)  # one wheel's fault: the other's
    assert factor([5.0, 0.95], 1.0) == pytest.approx(1.0)  # either side of the last: held
    assert factor([0.3, 1.0], 1.7) == pytest.approx(1.0)
    one = np.concatenate([[0.6, 0.0, 0.0, 0.0], [0.2, 0.0, 0.0, 0.0]])[None]  # one voter at x3
    assert float(observer._load_factor(one, 1.7)[0]) == pytest.approx(1.7)  # held


def test_friction_beyond_the_calibrated_speeds_is_allowed_between_its_extrapolations(model):
    """Calibrated at one speed, the friction at a third of it may be anything between the same
    (all Coulomb) and a third (all viscous): the allowance is the friction at the calibrated speed
    (same direction) times the relative distance, 2/3 of it; nothing within the range."""
    from youbot_fdi.fdi.observer import ModelObserver
    direction = np.array([1.0, -1.0, 1.0, -1.0]) / 2.0  # unit norm
    calibrated = 6.0  # [rad/s] the norm of the wheel speeds calibration drove at
    observer = ModelObserver(model, replace(FdiSettings(), calibrated_speed_range=(calibrated, calibrated)))
    slow = direction * calibrated / 3.0
    level_there = np.abs(observer.friction * direction * calibrated
                         + observer._coulomb(direction * calibrated)[1])
    np.testing.assert_allclose(observer._speed_extrapolation(slow), level_there * 2.0 / 3.0)
    np.testing.assert_allclose(observer._speed_extrapolation(direction * calibrated), 0.0)
    fast = direction * calibrated * 2.0  # twice as fast: all-viscous doubles it
    np.testing.assert_allclose(observer._speed_extrapolation(fast), level_there)
    assert ModelObserver(model, FdiSettings())._speed_extrapolation(slow) == 0.0  # no calibration


def test_evidence_that_drains_holds_no_new_alarm(model):
    """Two wheels' command residuals rise together (a shared change: no wheel fault) and fall
    back; the first drains at 1 a sample (score 0), the second at 0.5 (score 0.5), so after 7
    samples only the second is over the threshold, no longer shared. Evidence that drains tells of the
    shared excess, not of a fault now: no alarm. The second wheel's own excess after that (score
    2.5, evidence growing by 1.5 a sample from where it drained to) is one, on that wheel."""
    s = FdiSettings()
    decision = DecisionMaker(model.wheel_names, replace(s, breakaway_time=0.0), load_residual_data())
    n = len(model.wheel_names)

    def scores(first, second):
        f = frame(model, 0.0, 0.0)
        values = dict(f.values, command=np.array([first, second, 0.0, 0.0]))
        return values

    plan = [(3.0, 3.0)] * 4 + [(0.0, 0.5)] * 8 + [(0.0, 2.5)] * 4
    events = []
    for k, (first, second) in enumerate(plan):
        f = replace(frame(model, 10.0 + 0.01 * k, 0.0), values=scores(first, second))
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
    s = replace(FdiSettings(), breakaway_time=0.0)
    assert s.second_fault_score == 3.0 and s.evidence_cap == 3.0
    assert s.family_thresholds[FAMILIES.index('torque')] == s.family_thresholds[FAMILIES.index('command')] == 3.0
    plan = [(3.0, 0.0)] * 3 + [(3.0, 2.5)] * 10 + [(3.0, 3.5)] * 2

    def frames(plan):
        for k, (first, second) in enumerate(plan):
            f = frame(model, 10.0 + 0.01 * k, 0.0)
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


def test_the_command_path_allows_the_speed_error_of_a_torque_the_wheel_carries(model):
    """A wheel under its firmware's proportional gain k_p k_t answers a torque d it was not told
    of (a floor's drag) with the speed error d / (k_p k_t) (1 - exp(-t / tau)), tau = M_ii /
    (k_p k_t): the command bound allows that much of the torque residual the wheel carries, the
    same in one block and row by row, and from nothing again after a restart."""
    evaluator = ResidualEvaluator(model, FdiSettings())
    tau = evaluator.loop_time_constant
    stiffness = model.firmware.velocity_kp * model.drive.torque_per_amp
    np.testing.assert_allclose(tau, np.diag(model.dynamics.mass_matrix) / stiffness)
    assert evaluator.loop_compliance == pytest.approx(1.0 / stiffness)
    dt, rows, d = 0.01, 30, np.array([0.2, -0.1, 0.0, np.nan])  # [s], [N·m]; NaN: effort unknown
    step = np.full((rows, 1), dt)
    carried = evaluator._loop_disturbance(np.tile(d, (rows, 1)), step, np.zeros(rows, dtype=bool))
    t = dt * np.arange(1, rows + 1)[:, None]
    expected = np.where(np.isnan(d), 0.0, d) * -np.expm1(-t / tau)
    np.testing.assert_allclose(carried, expected, rtol=1e-12, atol=1e-15)
    row_by_row = ResidualEvaluator(model, FdiSettings())
    one = np.concatenate([row_by_row._loop_disturbance(d[None], step[:1], np.zeros(1, dtype=bool))
                          for _ in range(rows)])
    np.testing.assert_allclose(one, carried, rtol=1e-12)
    restarted = evaluator._loop_disturbance(d[None], step[:1], np.ones(1, dtype=bool))
    assert np.all(restarted == 0.0)
    # the bound: the larger of the unseen friction and the carried torque, through the compliance
    speed, target = np.full((1, 4), 2.0), np.full((1, 4), 2.0)
    args = (speed, np.zeros((1, 4)), speed, speed, target, target, target, np.ones((1, 1), dtype=bool),
            np.zeros((1, 1), dtype=bool))
    _, plain, *_ = evaluator._command_terms(*args, np.zeros((1, 4)), np.zeros((1, 4)), step[:1])
    _, allowed, *_ = evaluator._command_terms(*args, np.full((1, 4), 0.05), carried[-1:], step[:1])
    extra = np.maximum(0.05, np.abs(carried[-1])) / stiffness
    np.testing.assert_allclose(allowed - plain, extra[None])
    # a command sent but not yet acting: the step to it is allowed (velocity mode only)
    latest = target + np.array([[1.5, -0.5, 0.0, 2.0]])
    sent = (speed, np.zeros((1, 4)), speed, speed, target, target, latest)
    flags = (np.zeros((1, 1), dtype=bool), np.zeros((1, 4)), np.zeros((1, 4)), step[:1])
    _, ahead, *_ = evaluator._command_terms(*sent, np.ones((1, 1), dtype=bool), *flags)
    np.testing.assert_allclose(ahead - plain, np.abs(latest - target))
    _, effort_plain, *_ = evaluator._command_terms(*args[:7], np.zeros((1, 1), dtype=bool), *flags)
    _, effort_ahead, *_ = evaluator._command_terms(*sent, np.zeros((1, 1), dtype=bool), *flags)
    np.testing.assert_array_equal(effort_ahead, effort_plain)


def test_a_wheel_is_silent_from_its_first_sample_without_a_reading_not_across_a_gap(model):
    """Only a sample closed without a wheel's reading shows its module silent: after a gap with no
    samples at all (the stream or the host stalled: the base's comm_loss if it lasts), a wheel
    missing from the next sample has been silent 0 s, and its silence then grows with the
    samples it misses; any chunking of the rows gives the same times."""
    stamps = np.array([0.0, 0.01, 0.31, 0.32, 0.33, 0.34, 0.35])  # 0.3 s without any sample
    answered = np.ones((len(stamps), 4), dtype=bool)
    answered[2:6, 1] = False  # wheel 1 missing from the sample after the gap on
    answered[6, 3] = False  # wheel 3 misses one sample
    expected = np.zeros((len(stamps), 4))
    expected[2:6, 1] = stamps[2:6] - stamps[2]
    whole = ResidualEvaluator(model, FdiSettings()).silence(stamps, answered)
    np.testing.assert_allclose(whole, expected, atol=1e-12)
    chunked = ResidualEvaluator(model, FdiSettings())
    rows = [chunked.silence(stamps[k:k + 1], answered[k:k + 1]) for k in range(len(stamps))]
    np.testing.assert_allclose(np.concatenate(rows), expected, atol=1e-12)


def test_a_command_that_comes_after_samples_it_was_in_force_for_is_counted_late(model):
    """Live, a host behind may deliver a command after samples stamped later than it: those were
    judged without it (a replay of the same recording would not be), which the observer counts
    for the input diagnostics; a command for samples still to come is not late."""
    from youbot_fdi.fdi.observer import COMMANDS_LATE, ModelObserver
    from youbot_fdi.samples import CommandSample, JointSample
    settings = FdiSettings()
    observer = ModelObserver(model, settings)
    observer.command(CommandSample(0.0, 'velocity', np.zeros(4)))
    for stamp in (0.01, 0.02, 0.03):
        observer.update(JointSample(stamp, np.zeros(4), np.zeros(4), np.zeros(4)))
    observer.command(CommandSample(0.03 - settings.input_delay + 0.001, 'velocity', np.ones(4)))
    assert observer.counters[COMMANDS_LATE] == 0  # in force from after the last sample judged
    observer.command(CommandSample(0.02 - settings.input_delay, 'velocity', np.ones(4)))
    assert observer.counters[COMMANDS_LATE] == 1  # was in force at 0.02 and 0.03
    # the command path of every wheel starts again from the measured state and settles
    speeds = np.full(4, 0.5)
    prediction = observer.update(JointSample(0.04, np.zeros(4), speeds, np.zeros(4)))
    assert list(mask_wheels(prediction.resynced, 4)) == [True] * 4
    np.testing.assert_allclose(prediction.from_commands, model.kinematics.drive_signs * speeds)
    following = observer.update(JointSample(0.05, np.zeros(4), speeds, np.zeros(4)))
    assert not mask_wheels(following.resynced, 4).any()


def test_wheels_whose_speeds_fit_no_motion_slip_for_as_long_and_the_breakaway_after(model):
    """Speeds of a rigid motion never slip, however fast; a part no motion explains (the
    kinematics' null space) slips beyond the calibrated slip widened by its margin plus three
    speed_sigma (1.1 x 0.05 + 0.03 = 0.085 rad/s), and the base catches up for breakaway_time
    after; a row at a time gives the same rows. A base of three wheels always fits a motion."""
    settings = replace(FdiSettings(), calibrated_slip=0.05, speed_sigma=0.01)
    assert (settings.calibration_range_margin, settings.breakaway_time) == (0.1, 0.2)
    evaluator = ResidualEvaluator(model, settings)
    assert evaluator.slip_limit == pytest.approx(0.085)
    null = np.linalg.svd(model.kinematics.jacobian.T)[2][-1]  # orthogonal to every motion's speeds
    null = null / np.abs(null).max()
    rigid = model.kinematics.inverse(np.array([0.8, -0.5, 2.0]))  # a fast motion: no slip
    extra = np.zeros(40)
    extra[5], extra[10] = 0.08, 0.09  # under, then over the limit
    speeds = rigid + extra[:, None] * null
    stamps = 10.0 + 0.01 * np.arange(40)
    expected = (stamps >= stamps[10] - 1e-9) & (stamps - stamps[10] < 0.2 - 1e-9)
    assert evaluator.slipping(speeds, stamps).tolist() == expected.tolist()
    one_by_one = ResidualEvaluator(model, settings)
    rows = [bool(one_by_one.slipping(speeds[k:k + 1], stamps[k:k + 1])[0]) for k in range(40)]
    assert rows == expected.tolist()
    assert not ResidualEvaluator(model, FdiSettings()).slipping(speeds, stamps).any()  # inf: none
    robotino = load_model('robotino')
    three = replace(FdiSettings(), calibrated_slip=0.0, speed_sigma=1e-6)
    wild = np.random.default_rng(3).normal(0.0, 20.0, (50, 3))  # any speeds fit a motion
    assert not ResidualEvaluator(robotino, three).slipping(wild, stamps[:1] + np.arange(50)).any()


def test_the_parity_relations_confirm_a_wheel_alone_and_nothing_the_base_shares(model):
    """The youBot's one parity relation weighs every wheel by 1/2 (B = (+-1/2, ...)): a residual
    d on one wheel alone is confirmed in full; a force on the base (its range: a sideways drag,
    pattern (-1, 1, 1, -1)) not at all; a wheel's d beside that drag c by d / |d - c| (at most
    1); a residual pointing against what the relation says, 0. Slipping rows, missing residuals
    and a base of three wheels: 1 (nothing to say)."""
    evaluator = ResidualEvaluator(model, FdiSettings())
    basis = model.kinematics.parity_basis
    assert basis.shape == (4, 1) and np.allclose(np.abs(basis), 0.5)
    sideways = model.kinematics.jacobian[:, 1] / model.kinematics.jacobian[0, 0]  # (-1, 1, 1, -1)
    assert np.allclose(sideways, [-1.0, 1.0, 1.0, -1.0])
    d, c = 0.3, 0.1
    rows = np.array([[d, 0.0, 0.0, 0.0],
                     0.2 * sideways,
                     [d, 0.0, 0.0, 0.0] + c * sideways,  # wheel fl: d - c, the others +-c
                     [d, 0.0, 0.0, 0.0],
                     [np.nan, 0.1, 0.1, 0.1]])
    slipping = np.array([False, False, False, True, False])
    share = evaluator.parity_confirmed(rows, slipping)
    assert share[0].tolist() == [1.0, 1.0, 1.0, 1.0]  # the others have no residual to judge
    assert np.allclose(share[1], 0.0)
    assert share[2, 0] == pytest.approx(min(1.0, d / abs(d - c)))
    # B = +-(-1, -1, 1, 1)/2: the relation reads -d/2 (+-); fr alone would have to be +d (its
    # +c agrees: confirmed), bl alone -d (its +c points the other way: 0)
    assert np.allclose(np.sign(basis[:, 0]) * np.sign(basis[0, 0]), [1.0, 1.0, -1.0, -1.0])
    assert share[2, 1] == 1.0 and share[2, 2] == 0.0
    assert share[3].tolist() == [1.0] * 4 and share[4].tolist() == [1.0] * 4
    three = ResidualEvaluator(load_model('robotino'), FdiSettings())
    assert three.kinematics.parity_basis.shape == (3, 0)
    assert three.parity_confirmed(np.array([[0.5, -0.2, 0.1]]), np.zeros(1, dtype=bool)).tolist() == [[1.0] * 3]


def test_the_torque_shift_allows_the_friction_of_a_speed_the_reading_cannot_resolve():
    """Closed form, F_c a youBot's Coulomb level (0.03 N·m), v_s its step width 0.05 rad/s, the reading
    good to 3 x speed_sigma = 0.03 rad/s: a wheel read within 0.03 of standing may stand, and its
    friction may change by 2 F_c; at 0.06 by F_c (tanh(0.09 / 0.05) - tanh(0.03 / 0.05)); at
    2 rad/s practically not. The shift's scale is the learned bound plus that, times the load
    factor; a residual's step of 1.5 F_c on a wheel that creeps is then inside the shift test's
    drift (no alarm), the same step at a resolved speed alarms."""
    from youbot_fdi.model.profile import PlatformModel
    base = load_model('youbot')
    model = PlatformModel(replace(base.profile, dynamics=replace(base.profile.dynamics,
                                                                 coulomb_friction=(0.03,) * 4)))
    settings = replace(FdiSettings(), speed_sigma=0.01, breakaway_time=0.0)
    dynamics = model.dynamics
    coulomb, width = dynamics.coulomb, dynamics.parameters.coulomb_velocity_scale
    assert width == 0.05 and coulomb.tolist() == [0.03] * 4
    speeds = np.array([[0.0, -0.03, 0.06, 2.0]])
    expected = coulomb * np.array([2.0, 2.0, math.tanh(0.09 / 0.05) - math.tanh(0.03 / 0.05),
                                   math.tanh(2.03 / 0.05) - math.tanh(1.97 / 0.05)])
    np.testing.assert_allclose(dynamics.coulomb_span(speeds, 0.03), expected[None], rtol=1e-12)
    assert dynamics.coulomb_span(np.full(4, 0.06), 0.0).tolist() == [0.0] * 4  # an exact reading
    evaluator = ResidualEvaluator(model, settings)
    learned = np.full((1, 4), 0.1)
    np.testing.assert_allclose(evaluator.shift_scale(learned, speeds, np.array([[1.5]])),
                               learned + 1.5 * expected[None], rtol=1e-12)

    learned_scale = 0.05  # [N·m]: a step of 1.5 F_c is 0.9 of it, 0.41 of it with 2 F_c more

    def first_shift_alarm(speed):
        decision = DecisionMaker(model.wheel_names, settings, load_residual_data())
        n, bound = len(model.wheel_names), np.ones(len(model.wheel_names))
        velocity = np.array([speed, 2.0, 2.0, 2.0])
        scale = evaluator.shift_scale(np.full((1, n), learned_scale), velocity[None], 1.0)[0]
        for k in range(600):
            values = {f: np.zeros(n) for f in FAMILIES}
            values['torque'][0] = 0.0 if k < 400 else 1.5 * coulomb[0]  # inside the bound (1)
            row = ResidualFrame(stamp=10.0 + k / 100.0, values=values,
                                bounds={f: bound for f in FAMILIES}, velocity=velocity,
                                torque=np.full(n, 0.5), velocity_mode=True, command=velocity,
                                frozen=np.zeros(n, dtype=int), effort_frozen=np.zeros(n, dtype=int),
                                position_frozen=np.zeros(n, dtype=int), silent=np.zeros(n),
                                torque_scale=scale)
            if any(e.level == 'ERROR' for e in decision.update(row)):
                return k
        return None

    assert 1.5 * coulomb[0] / (learned_scale + 2.0 * coulomb[0]) < settings.shift_drift
    assert first_shift_alarm(0.01) is None  # never evidence
    # the shift 0.9 decays as the level follows (a = exp(-dt / shift_time_constant) a sample);
    # its CUSUM sum_j (0.9 a^j - drift) reaches shift_threshold after J samples
    keep, total, samples = math.exp(-0.01 / settings.shift_time_constant), 0.0, 0
    while total < settings.shift_threshold:
        total += 0.9 * keep ** samples - settings.shift_drift
        samples += 1
    assert first_shift_alarm(2.0) == pytest.approx(400 + samples - 1, abs=1)  # as above: +-1 row
