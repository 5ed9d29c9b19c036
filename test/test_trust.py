"""Mechanisms of issue 32 that keep the FDI quiet where calibration did not reach, each checked
against a hand-derived closed form: evidence per second whatever the rate, bounds that widen
beyond the calibrated range, a command path that does not predict a current calibration never
saw, a frozen-reading test that needs a turning wheel, and a load factor without a clamp."""
from dataclasses import replace
import math

import numpy as np
import pytest

from youbot_fdi.fdi.decision import DecisionMaker
from youbot_fdi.app.config import load_residual_data
from youbot_fdi.fdi.residuals import (BOUND_TERMS, FAMILIES, FROZEN_MIN_TICKS, FROZEN_NOISE_SIGMAS,
                                      PRIOR_SETTINGS, ResidualEvaluator, ResidualFrame, bound_weights)
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.model import load_model


@pytest.fixture(scope='module')
def model():
    return load_model('youbot')


def frame(model, stamp, torque_score):
    n = len(model.wheel_names)
    values = {f: np.zeros(n) for f in FAMILIES}
    values['torque'] = np.array([torque_score, 0.0, 0.0, 0.0])
    return ResidualFrame(stamp=stamp, values=values, bounds={f: np.ones(n) for f in FAMILIES},
                         velocity=np.full(n, 2.0), torque=np.full(n, 0.5), command_mode='velocity',
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
    low = observer.update(JointSample(0.03, np.zeros(4), speeds + 0.2, np.full(4, 0.1)))
    assert np.all(np.abs(low.from_commands - held) > 1e-6)  # predicting again, from that state


def test_a_noisy_speed_reading_at_rest_is_not_a_turning_wheel(model):
    """The frozen-position test counts a wheel as turning only where its speed less
    FROZEN_NOISE_SIGMAS x speed_sigma moves the encoder by FROZEN_MIN_TICKS in the interval."""
    sigma = 0.05  # [rad/s]
    evaluator = ResidualEvaluator(model, replace(FdiSettings(), speed_sigma=sigma))
    step = 0.002  # 500 Hz
    needed = FROZEN_MIN_TICKS * evaluator.position_quantum / step + FROZEN_NOISE_SIGMAS * sigma
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

    def factor(ratios):
        return observer._load_factor(np.concatenate([np.array(ratios) * friction, friction]), 1.0)

    assert factor([3.2, 3.0, 3.4, 3.1])[0] == pytest.approx(3.15)
    assert factor([5.0, 1.0, 1.0, 1.0])[0] == pytest.approx(1.0)
    assert factor([3.3, 1.0, 3.3, 3.2])[0] == pytest.approx(3.25)
    two_votes = np.concatenate([np.array([3.0, 3.0, 0.0, 0.0]) * friction, [0.2, 0.2, 0.0, 0.0]])
    assert observer._load_factor(two_votes, 1.7) == (pytest.approx(1.0), False)  # kept: too few


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
