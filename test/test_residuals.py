"""``youbot_fdi/fdi/residuals.py``: the residual evaluator's bounds (widening beyond the
calibrated range, the remembered transient, the loop's compliance), the
frozen-reading and silence tests, slip, the parity relations and the torque shift's scale; each
against a hand-derived closed form."""
from dataclasses import replace
import math

import numpy as np
import pytest

from youbot_fdi.fdi.decision import DecisionMaker
from youbot_fdi.app.config import load_residual_data
from youbot_fdi.fdi.residuals import (BOUND_TERMS, FAMILIES, FROZEN_MIN_TICKS, SPEED_NOISE_SIGMAS,
                                      PRIOR_SETTINGS, ResidualBatch, ResidualEvaluator, ResidualFrame,
                                      bound_weights, scores)
from youbot_fdi.fdi.recursions import shifted
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.model import load_model
from youbot_fdi.model.firmware import slowest_time_constant
from youbot_fdi.samples import JointSample

FAST_EXCEPT = ()  # `make check`: every test here (the unit tests of the core, under a minute)


@pytest.fixture(scope='module')
def model():
    return load_model('youbot')


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


def test_the_command_bound_remembers_a_transient_as_the_loop_does(model):
    """The command bound's transient part, T = w_s min(step, range) + w_a min(acceleration,
    range) plus every feature's excess X beyond calibration's range weighed w (the larger of the
    learned and the default weight), is remembered: the rows after it keep the peak
    max(T_k, T_0 exp(-(t - t_0) / tau)) less their own T_k, tau the loop's slowest time constant
    (the time a guessed start takes to fade); the same row by row; nothing while settling,
    nothing from before a restart, nothing for a current-mode row. A step within the range is
    remembered as one beyond it is: the model's loop may be slower than identified."""
    learned = dict(zip(BOUND_TERMS['command'], (0.02, 0.01, 0.05, 0.004)))
    settings = replace(FdiSettings(), command_feature_range=(math.inf, 10.0, 3.0, 5.0), **learned)
    evaluator = ResidualEvaluator(model, settings)
    tau = slowest_time_constant(model.dynamics, model.drive.torque_per_amp, model.firmware)
    weight = max(learned['command_delay'], bound_weights(PRIOR_SETTINGS, 'command')[3])
    rows, dt, excess = 12, 0.01, 20.0  # [rad/s²] beyond the range, on wheel 1 only
    stamp = 100.0 + dt * np.arange(rows)
    features = np.tile([1.0, 2.0, 0.5, 1.0], (rows, 4, 1))
    features[0, 1, 3] = 5.0 + excess
    features[0, 2, 2] = 2.5  # a step of 2.5 rad/s on wheel 2, within the range (3)
    mode, calm = np.ones(rows, dtype=bool), np.zeros((rows, 4), dtype=bool)
    fresh = np.zeros(rows, dtype=bool)
    added = evaluator._remembered_transient(features, mode, calm, stamp, fresh)
    steady = 0.5 * learned['command_transient_fraction'] + 1.0 * learned['command_delay']
    peaks = np.array([0.0, 0.5 * learned['command_transient_fraction'] + 5.0 * learned['command_delay']
                      + weight * excess,
                      2.5 * learned['command_transient_fraction'] + learned['command_delay'], 0.0])
    expected = np.zeros((rows, 4))
    expected[1:] = np.maximum(0.0, peaks * np.exp(-(stamp[1:, None] - stamp[0]) / tau) - steady)
    assert expected[1:, 1:3].min() > 0.0 and np.all(expected[:, [0, 3]] == 0.0)
    np.testing.assert_allclose(added, expected, rtol=1e-9, atol=1e-12)
    assert evaluator.bound('command', features[:1])[0, 1] == pytest.approx(
        features[0, 1] @ np.array(list(learned.values())) - 20.0 * learned['command_delay']
        + weight * excess)  # the row itself: its own excess, in the bound already
    one_by_one = ResidualEvaluator(model, settings)
    by_row = np.concatenate([one_by_one._remembered_transient(
        features[k:k + 1], mode[k:k + 1], calm[k:k + 1], stamp[k:k + 1], fresh[k:k + 1])
        for k in range(rows)])
    np.testing.assert_array_equal(by_row, added)
    settling = evaluator._remembered_transient(features, mode, ~calm, stamp + 1.0, fresh)
    assert np.all(settling == 0.0)
    restart = fresh.copy()
    restart[3] = True
    after = ResidualEvaluator(model, settings)._remembered_transient(features, mode, calm, stamp,
                                                                     restart)
    np.testing.assert_allclose(after[:3], expected[:3], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(after[3:], 0.0, atol=1e-12)  # the rows' own transients only
    current_mode = mode.copy()
    current_mode[2:] = False  # an effort bound [N·m] takes nothing of the speed's memory
    mixed = ResidualEvaluator(model, settings)._remembered_transient(features, current_mode, calm,
                                                                     stamp, fresh)
    np.testing.assert_allclose(mixed[:2], expected[:2], rtol=1e-9, atol=1e-12)
    assert np.all(mixed[2:] == 0.0)


def _pushing_away(evaluator, velocity, torque, target, latest, mode, restart, step=0.01):
    """``_excess_pushing_away`` over rows of one interval ``step`` [s], each row's sample before
    being the row above (the first's: itself)."""
    previous = shifted(velocity[0], velocity)
    return evaluator._excess_pushing_away(velocity, previous, torque, target, latest, mode, restart,
                                          np.full((len(velocity), 1), step))


def test_a_current_that_rises_pushing_away_from_the_command_is_no_live_loop(model):
    """A PI loop's output changes by k_p (e - e_0) + k_i (the error summed): while its current
    pushes a wheel away from its command (beyond three torque_sigma, the error beyond three
    speed_sigma, the error to the latest command sent of the same sign) and the error does not
    shrink, that current can only fall, by at least k_p k_t times the error's growth (not past
    zero). What it stands above that since the stretch began is counted (0 where it fell enough,
    where the error shrank, where the current pushes toward the command, where the latest
    command lies the other way, in current mode, after a restart, with ``loop_direction`` off);
    the same row by row. Here the speed stands still (no lag to allow)."""
    sigma = 0.05  # [N·m]; three of it: 0.15
    evaluator = ResidualEvaluator(model, replace(FdiSettings(), torque_sigma=sigma, speed_sigma=0.02))
    stiffness = evaluator.loop_stiffness  # [N·m per rad/s]
    assert stiffness == pytest.approx(model.firmware.velocity_kp * model.drive.torque_per_amp)
    rows = 6
    velocity = np.tile([2.0, 2.0, 2.0, 2.0], (rows, 1))
    velocity[:, 2] = 2.0 - 0.1 * np.arange(rows)  # wheel 2 nears its command (0)
    target = np.zeros((rows, 4))
    target[:, 0] = [0.0, 0.0, -0.5, -0.5, -1.0, -1.0]  # wheel 0's error grows: -2 .. -3 rad/s
    latest = target.copy()
    latest[3, 0] = 3.0  # sent, not yet in force: the loop may already chase it (toward)
    torque = np.column_stack([[0.3, 0.35, 0.4, 0.45, 0.5, 0.6],    # rises: no live loop's
                              [0.5, 0.45, 0.4, 0.35, 0.3, 0.25],   # falls: a loop unwinding
                              [0.3, 0.35, 0.4, 0.45, 0.5, 0.55],   # rises, but the error shrinks
                              np.full(rows, -0.4)])                # pushes toward the command
    mode, fresh = np.ones(rows, dtype=bool), np.zeros(rows, dtype=bool)
    excess = _pushing_away(evaluator, velocity, torque, target, latest, mode, fresh)
    expected = np.zeros((rows, 4))
    # from 0.3 at the start; row 2's error grew by 0.5 rad/s, so a live loop's current had
    # fallen by min(0.5 k_p k_t, 0.3); row 3 is no stretch (the latest command lies beyond the
    # speed), so row 4 starts a new one at 0.5 (error 3), which row 5 (error 3) rose 0.1 above
    expected[:, 0] = [0.0, 0.05, 0.1 + min(0.5 * stiffness, 0.3), 0.0, 0.0, 0.1]
    np.testing.assert_allclose(excess, expected, atol=1e-12)
    one_by_one = ResidualEvaluator(model, evaluator.settings)
    previous = shifted(velocity[0], velocity)
    by_row = np.concatenate([one_by_one._excess_pushing_away(
        velocity[k:k + 1], previous[k:k + 1], torque[k:k + 1], target[k:k + 1], latest[k:k + 1],
        mode[k:k + 1], fresh[k:k + 1], np.full((1, 1), 0.01)) for k in range(rows)])
    np.testing.assert_array_equal(by_row, excess)
    restart = fresh.copy()
    restart[1] = True  # the stretch starts again at row 2 (0.4, error 2.5)
    again = _pushing_away(ResidualEvaluator(model, evaluator.settings), velocity, torque, target,
                          latest, mode, restart)
    np.testing.assert_allclose(again[:, 0], [0.0, 0.0, 0.0, 0.0, 0.0, 0.1], atol=1e-12)
    current_mode = mode.copy()
    current_mode[:2] = False
    mixed = _pushing_away(ResidualEvaluator(model, evaluator.settings), velocity, torque, target,
                          latest, current_mode, fresh)
    np.testing.assert_allclose(mixed[:, 0], [0.0, 0.0, 0.0, 0.0, 0.0, 0.1], atol=1e-12)
    unsigned = ResidualEvaluator(model, evaluator.settings)
    unsigned.signed_effort = False  # a magnitude has no direction to judge
    assert np.all(_pushing_away(unsigned, velocity, torque, target, latest, mode, fresh) == 0.0)
    off = ResidualEvaluator(model, replace(evaluator.settings, loop_direction=False))  # identify's runs
    assert np.all(_pushing_away(off, velocity, torque, target, latest, mode, fresh) == 0.0)
    # judged as the command residual: the speed error, scored excess / (3 sqrt(2) sigma), where
    # that is more than the path's own score, and wherever the path is not judged (settling)
    residual, bound = np.full((rows, 4), 0.3), np.full((rows, 4), 1.0)  # the path's: 0.3
    settling = np.zeros((rows, 4), dtype=bool)
    settling[1, 0] = True
    error = velocity - target
    judged_r, judged_u = evaluator._judge_loop_direction(residual, bound, settling, error, excess)
    noise = 3.0 * math.sqrt(2.0) * sigma  # 0.212 N·m: row 5 (0.1) scores 0.47, row 1 0.24
    picked = np.zeros((rows, 4), dtype=bool)
    picked[[1, 2, 5], 0] = True  # row 1 scores below the path, but the path is not judged there
    np.testing.assert_allclose(np.abs(judged_r) / judged_u,
                               np.where(picked, excess / noise, 0.3), rtol=1e-12)
    np.testing.assert_array_equal(judged_r, np.where(picked, error, residual))


def test_a_live_loop_turns_its_current_round_as_its_error_grows_read_through_the_lag(model):
    """Where the error to the command grew by d since a wheel began pushing away, a live loop's
    current has fallen by k_p k_t d (not past zero); the host's reading may trail the firmware's
    by the input delay tau, and its speed and current stand for instants up to one interval dt
    apart, so (tau + dt) times the reading's rate of change at both ends comes off d first; an
    unknown rate takes no growth, and a torque at the current limit is asked no fall (a
    saturated output may hold there), and an error that has not grown past the lag's allowance
    has not been seen to keep from shrinking (nothing counted). Closed forms over 5 rows of 10
    ms, tau 40 ms: the error grows 2.0, 2.2, 2.4, 2.4, 2.4 rad/s (rates 0, 20, 20, 0, 0 rad/s^2)."""
    lag, step = 0.04, 0.01  # [s]
    evaluator = ResidualEvaluator(model, replace(FdiSettings(), torque_sigma=0.05, speed_sigma=0.02,
                                                 input_delay=lag))
    stiffness = evaluator.loop_stiffness  # 0.76 N·m per rad/s
    rows = 5
    distance = np.array([2.0, 2.2, 2.4, 2.4, 2.4])
    velocity = np.tile(distance[:, None], (1, 4))  # every command 0: the error is the speed
    target = latest = np.zeros((rows, 4))
    live = 1.0 - stiffness * (distance - 2.0)  # [N·m] a live loop's current, from 1 N·m
    # pushing away: the error (command less speed) is negative, the torques positive
    torque = np.column_stack([live, np.ones(rows), np.ones(rows), [0.1, 1.0, 1.0, 1.0, 1.0]])
    previous = shifted(velocity[0], velocity)
    previous[3, 2] = np.nan  # wheel 2: its rate unknown in row 3
    mode, fresh = np.ones(rows, dtype=bool), np.zeros(rows, dtype=bool)
    excess = evaluator._excess_pushing_away(velocity, previous, torque, target, latest, mode,
                                            fresh, np.full((rows, 1), step))
    held = min(stiffness * 0.4, 1.0)  # rows 3-4: grown 0.4 - (tau + dt) 0; rows 1-2 grow nothing
    np.testing.assert_allclose(excess[:, 0], 0.0, atol=1e-12)  # a live loop: nothing
    # a current held at 1 N·m (a runaway): rows 1 and 2 grew 0.2 and 0.4 rad/s in the reading,
    # less (0.04 + 0.01) s x 20 rad/s^2 = 1 rad/s the reading may have trailed by
    np.testing.assert_allclose(excess[:, 1], [0.0, 0.0, 0.0, held, held], atol=1e-12)
    np.testing.assert_allclose(excess[:, 2], [0.0, 0.0, 0.0, 0.0, held], atol=1e-12)
    # wheel 3 begins at row 1 (0.1 N·m is within three torque_sigma): from 2.2 rad/s at 20
    # rad/s^2, rows 3-4 grew 0.2 - 0.05 x 20 < 0
    np.testing.assert_allclose(excess[:, 3], 0.0, atol=1e-12)
    # the speed and the current need not stand for one instant of a sample's interval: with no
    # input delay, the interval (10 ms) times the rates still comes off: row 1 grew 0.2 - 0.01 x
    # 20, row 2 0.4 - 0.01 x 20, rows 3-4 0.4
    no_delay = ResidualEvaluator(model, replace(evaluator.settings, input_delay=0.0))
    at_once = no_delay._excess_pushing_away(velocity, previous, torque, target, latest, mode, fresh,
                                            np.full((rows, 1), step))
    np.testing.assert_allclose(at_once[:, 1], [0.0, 0.0, 0.2 * stiffness, held, held], atol=1e-12)
    # a torque at the current limit is asked no fall: a saturated output may hold there
    saturated = torque.copy()
    saturated[:, 1] = model.drive.max_torque
    at_limit = ResidualEvaluator(model, evaluator.settings)._excess_pushing_away(
        velocity, previous, saturated, target, latest, mode, fresh, np.full((rows, 1), step))
    np.testing.assert_allclose(at_limit[:, 1], 0.0, atol=1e-12)
    np.testing.assert_allclose(at_limit[:, 2], excess[:, 2], atol=1e-12)
    # an error read no larger than the lag can explain has not been seen to keep from shrinking:
    # a current rising 1.0 -> 1.1 N·m while the reading's error went 2.0 -> 2.2 at 20 rad/s^2
    # (grown 0.2 - 0.05 x 20 < 0) counts nothing in that row; held there a row (rate 0), the
    # error grew 0.2 and the loop should have fallen by 0.2 k_p k_t
    rising = np.tile(np.array([[2.0], [2.2], [2.2]]), (1, 4))
    rise = np.tile(np.array([[1.0], [1.1], [1.1]]), (1, 4))
    counted = ResidualEvaluator(model, evaluator.settings)._excess_pushing_away(
        rising, shifted(rising[0], rising), rise, np.zeros((3, 4)), np.zeros((3, 4)),
        np.ones(3, dtype=bool), np.zeros(3, dtype=bool), np.full((3, 1), step))
    np.testing.assert_allclose(counted[:, 0], [0.0, 0.0, 0.1 + 0.2 * stiffness], atol=1e-12)


def test_a_noisy_speed_reading_at_rest_is_not_a_turning_wheel(model):
    """The frozen-position test counts a wheel as turning only where its speed less
    SPEED_NOISE_SIGMAS x speed_sigma moves the encoder by FROZEN_MIN_TICKS in the interval."""
    sigma = 0.05  # [rad/s]
    evaluator = ResidualEvaluator(model, replace(FdiSettings(), speed_sigma=sigma))
    step = 0.002  # 500 Hz
    needed = FROZEN_MIN_TICKS * evaluator.position_quantum / step + SPEED_NOISE_SIGMAS * sigma
    speeds = np.array([[0.5 * needed, 0.99 * needed, 1.01 * needed, 3 * needed]])
    moving = evaluator._moving(speeds, np.zeros((1, 4)), np.array([[False]]), step, np.zeros((1, 4)),
                               np.zeros((1, 4)))
    assert moving.tolist() == [[False, False, True, True]]


def test_a_lagging_speed_reading_after_a_stop_is_not_a_turning_wheel(model):
    """A reading that lags the wheel by tau (first order) decays as w exp(-t / tau) after the
    wheel stops: it changes by w dt / tau a sample, so the encoder bound's change term, learned
    as tau / dt (``encoder_change_fraction``), allows w dt of position the reading claims and
    the encoder never shows. The frozen-position test takes the speed less that bound: the
    decaying reading is never a turning wheel (its position repeats at every speed), while a
    steady reading is one from sigma + FROZEN_MIN_TICKS ticks a sample."""
    tau, dt, sigma = 0.04, 0.008, 0.0005  # [s], [s], [rad]
    settings = replace(FdiSettings(), speed_sigma=0.0, encoder_sigma=sigma, encoder_speed_fraction=0.0,
                       encoder_change_fraction=tau / dt, timing_jitter=0.0)
    evaluator = ResidualEvaluator(model, settings)
    speed = np.array([[0.2, 1.0, 4.0, 10.0]])  # [rad/s], each far above two ticks a sample
    quantum = evaluator.position_quantum
    assert np.all(speed * dt > FROZEN_MIN_TICKS * quantum + sigma)
    position = np.zeros((1, 4))
    for change, expected in ((-speed * dt / tau, [False] * 4), (np.zeros((1, 4)), [True] * 4)):
        _, features = evaluator._encoder_terms(position, position, speed, change, dt)
        bound = evaluator.bound('encoder', features)
        np.testing.assert_allclose(bound, sigma + np.abs(change) * tau)  # the closed form
        moving = evaluator._moving(speed, np.zeros((1, 4)), np.array([[False]]), dt, bound, np.zeros((1, 4)))
        assert moving.tolist() == [expected]


def test_the_other_wheels_witness_a_frozen_reading_of_the_one_repeated_wheel(model):
    """Four mecanum wheels have one parity relation, B = +-(1/2, ...), so a reading off by e on
    one wheel reads e/4 on each wheel's relation: the other wheels' rigid motion gives the wheel
    its true speed back exactly. The witness takes it less slip_limit / |B_w|^2 (1.1 x 0.05 +
    3 x 0.01 = 0.085 rad/s over 1/4: 0.34 rad/s), that tolerance times the row's largest torque
    over calibrated_effort where larger (force 2: 0.68 rad/s); only for the row's one wheel whose
    position repeated (two cannot be told apart) and whose speed reading repeated too (a
    blocked wheel's noisy reading does not), nothing where a torque or a speed is unknown or on
    three wheels. In current mode a repeated position of a wheel witnessed turning two ticks is
    frozen; in velocity mode the command and the reading witness, as before."""
    settings = replace(FdiSettings(), calibrated_slip=0.05, speed_sigma=0.01, calibrated_effort=0.5)
    evaluator = ResidualEvaluator(model, settings)
    assert evaluator._rigid_tolerance == pytest.approx(np.full(4, 0.34))
    true = model.kinematics.inverse(np.array([0.2, -0.05, 0.2]))  # [rad/s]
    frozen = true.copy()
    frozen[0] = 0.0  # an encoder-derived reading freezes at 0
    np.testing.assert_allclose(evaluator.rigid_speed(frozen[None])[0, 0], true[0], rtol=1e-12)
    np.testing.assert_allclose(evaluator.rigid_speed(true[None]), true[None], atol=1e-12)  # rigid: itself
    speeds = np.tile(frozen, (5, 1))
    one, two = [True, False, False, False], [True, False, True, False]
    repeated = np.array([one, one, two, one, one])
    torque = np.full((5, 4), 0.3)
    torque[1, 2] = -1.0  # twice the calibrated effort
    torque[3, 1] = np.nan
    none, start = np.zeros((1, 4), dtype=bool), np.zeros(1, dtype=bool)
    # the row before, in which the wheel's position moved with readings that fitted the motion
    assert not evaluator._rigid_witness(true[None], true[None], none, none, torque[:1], start).any()
    witnessed = evaluator._rigid_witness(speeds, speeds, repeated, repeated, torque,
                                         np.zeros(5, dtype=bool))
    expected = np.zeros((5, 4))
    expected[[0, 4], 0] = abs(true[0]) - 0.34
    expected[1, 0] = abs(true[0]) - 0.68
    assert abs(true[0]) > 0.68
    np.testing.assert_allclose(witnessed, expected, atol=1e-12)
    step = 0.01
    current_mode = np.zeros((5, 1), dtype=bool)
    moving = evaluator._moving(speeds, np.zeros((5, 4)), current_mode, step, np.zeros((5, 4)), witnessed)
    assert moving[:, 0].tolist() == [True, True, False, False, True]
    velocity_mode = ~current_mode
    assert not evaluator._moving(speeds, np.zeros((5, 4)), velocity_mode, step, np.zeros((5, 4)),
                                 witnessed)[:, 0].any()
    three = ResidualEvaluator(load_model('robotino'), settings)
    unread = speeds.copy()
    unread[:, 2] = np.nan  # a wheel without a speed reading: no rigid motion to witness
    unmarked = np.zeros(5, dtype=bool)
    assert not evaluator._rigid_witness(unread, unread, repeated, repeated, torque, unmarked).any()
    noisy = np.zeros_like(repeated)  # the same positions, a speed reading that changed (blocked)
    assert not evaluator._rigid_witness(speeds, speeds, repeated, noisy, torque, unmarked).any()
    alone = np.array([[True, False, False]])
    assert not three._rigid_witness(np.array([[0.0, 2.0, -2.0]]), np.zeros((1, 3)), alone, alone,
                                    np.zeros((1, 3)), start).any()


def test_a_wheel_that_stood_off_the_base_when_its_position_last_moved_is_not_witnessed(model):
    """The witness counts only what it says beyond how far the wheel's reading stood off the
    others' rigid motion (its parity error) in the row its position last moved: a wheel standing
    under a small current while the others' motion says it turns (its contacts sliding, its
    position creeping a tick now and then) stood off by all of that speed then, and repeats its
    position without a freeze (witnessed |true| - 0.34 - |true| < 0: nothing). Once it has moved
    with the base again (parity error 0), a repeat is witnessed as before; at a restart the
    row's own readings stand for the last move (here standing off: nothing after it)."""
    settings = replace(FdiSettings(), calibrated_slip=0.05, speed_sigma=0.01, calibrated_effort=0.5)
    evaluator = ResidualEvaluator(model, settings)
    true = model.kinematics.inverse(np.array([0.2, -0.05, 0.2]))  # [rad/s]
    standing = true.copy()
    standing[0] = 0.0  # the wheel reads 0 (it stands, or its encoder froze)
    # standing off the motion by all of the wheel's true speed; the rigid motion: not at all
    np.testing.assert_allclose(abs(evaluator._parity_alone(standing[None])[0, 0]), abs(true[0]))
    assert abs(evaluator._parity_alone(true[None])[0, 0]) < 1e-12
    speeds = np.array([standing, standing, standing, true, standing, standing, standing])
    moved = [False] * 4
    first = [True, False, False, False]
    repeated = np.array([moved, first, first, moved, first, first, first])
    restart = np.array([False, False, False, False, False, True, False])
    torque = np.full((7, 4), 0.3)
    witnessed = evaluator._rigid_witness(speeds, speeds, repeated, repeated, torque, restart)
    expected = np.zeros((7, 4))
    expected[4, 0] = abs(true[0]) - 0.34  # after a move with the base; not after the restart
    np.testing.assert_allclose(witnessed, expected, atol=1e-12)
    # row by row (the live path), the same
    live = ResidualEvaluator(model, settings)
    rows = [live._rigid_witness(speeds[k:k + 1], speeds[k:k + 1], repeated[k:k + 1],
                                repeated[k:k + 1], torque[k:k + 1], restart[k:k + 1])
            for k in range(7)]
    np.testing.assert_allclose(np.concatenate(rows), expected, atol=1e-12)
    # restarted with the base at rest (every reading fits): a wheel frozen since is witnessed
    # once the base moves
    rested = ResidualEvaluator(model, settings)
    rested.restart(JointSample(0.0, np.zeros(4), np.zeros(4), np.zeros(4)))
    frozen = rested._rigid_witness(standing[None], standing[None], repeated[1:2], repeated[1:2],
                                   torque[:1], restart[:1])
    np.testing.assert_allclose(frozen[0], [abs(true[0]) - 0.34, 0.0, 0.0, 0.0], atol=1e-12)


def test_an_encoder_residual_is_evidence_only_where_a_reading_stopped(model):
    """The encoder bound is judged as learned where the residual is at least half the larger
    of the position's change and the speed readings' (a frozen position: all of the speed's; a
    speed reading forced to zero: all of the position's; the interval a stop falls in: half);
    elsewhere at least the residual itself, a score of at most 1 (both readings moved: the
    speed's variation inside the interval, no stopped reading). A residual not known stays
    unknown (silent)."""
    bound = np.full(6, 0.002)
    turned = np.array([0.0, 0.1, 0.1, 0.087, 0.2, np.nan])  # [rad]
    read = np.array([0.1, 0.0, 0.05, 0.1, 0.193, 0.1])  # [rad]
    residual = turned - read
    judged = ResidualEvaluator._stopped_reading_bound(residual, bound, turned, read)
    np.testing.assert_allclose(judged[:3], bound[:3])  # stopped: a position, a speed, half
    np.testing.assert_allclose(judged[3:5], [0.013, 0.007])  # moved together: at least |r|
    assert np.isnan(judged[5])
    z = scores(residual, judged)
    assert z[3] == pytest.approx(1.0) and z[4] == pytest.approx(1.0) and z[5] == 0.0
    assert (z[:3] >= 25.0).all()


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


def test_the_command_path_allows_a_lag_the_other_wheels_share_not_one_wheels_own(model):
    """A lag every other wheel needs (r_j = lag x a_j within the noise floor s) is allowed to a
    wheel, the least of it that fits them all, times its own acceleration; one wheel's departure
    (a fault), a single other wheel's need, or a wheel not judged widens nothing. Worked by hand
    with s = 0.1 rad/s: the intervals [(r - s) / a, (r + s) / a] of the lag [s]."""
    evaluator = ResidualEvaluator(model, FdiSettings())
    noise = np.full((3, 4), 0.1)
    residual = np.array([[0.8, -0.4, -0.6, 0.05],   # three lag alike; the fourth stands (a = 0)
                         [2.0, 0.02, -0.03, 0.0],   # wheel 0 departs alone
                         [0.8, -0.4, 0.0, 0.0]])    # one other wheel needs a lag: not shared
    acceleration = np.array([[-20.0, 10.0, 15.0, 0.0],
                             [-20.0, 10.0, 15.0, 12.0],
                             [-20.0, 10.0, 0.0, 0.0]])
    voting = np.ones((3, 4), dtype=bool)
    allowed = evaluator._shared_lag(residual, acceleration, noise, voting)
    # row 0, wheel 0: wheels 1 and 2 need [-0.05, -0.03] and [-0.7/15, -0.5/15]: -1/30 at least;
    # wheel 1: [-0.045, -0.035] and [-0.7/15, -0.5/15] -> -0.035; wheel 2: -0.035 too
    expected = np.array([[20.0 / 30.0, 0.35, 0.035 * 15.0, 0.0], [0.0] * 4, [0.0] * 4])
    np.testing.assert_allclose(allowed, expected, rtol=1e-12, atol=1e-15)
    # a batch of one per row: the same
    for row in range(3):
        one = evaluator._shared_lag(residual[row:row + 1], acceleration[row:row + 1],
                                    noise[row:row + 1], voting[row:row + 1])
        np.testing.assert_allclose(one[0], expected[row], rtol=1e-12, atol=1e-15)
    # wheel 1 not judged (its prediction settling): wheels 0 and 2 each keep one voter only
    silenced = voting.copy()
    silenced[0, 1] = False
    assert np.all(evaluator._shared_lag(residual, acceleration, noise, silenced)[0, [0, 2]] == 0.0)
    # the command bound (velocity mode) widens by just that: r = measured - predicted speed,
    # a = the prediction's change over the interval; the noise floor its constant and speed terms
    # (the defaults': 0.7 rad/s at 2 rad/s, so five times row 0's residuals)
    lagging = 5.0 * residual[:1]
    step = np.full((1, 1), 0.01)
    speed, target = np.full((1, 4), 2.0), np.full((1, 4), 2.0)
    before = speed - acceleration[:1] * step
    flags = (np.ones((1, 1), dtype=bool), np.zeros((1, 4), dtype=bool), np.zeros((1, 4)),
             np.zeros((1, 4)), step)
    _, plain, features, _ = evaluator._command_terms(speed, np.zeros((1, 4)), speed, before, target,
                                                     target, target, *flags)
    _, widened, *_ = evaluator._command_terms(speed + lagging, np.zeros((1, 4)), speed, before,
                                              target, target, target, *flags)
    floor = features[..., :2] @ bound_weights(FdiSettings(), 'command')[:2]
    shared = evaluator._shared_lag(lagging, acceleration[:1], floor, np.ones((1, 4), dtype=bool))
    assert shared[0, 0] > 0.0
    np.testing.assert_allclose(widened - plain, shared, rtol=1e-12, atol=1e-12)


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


def extrapolating(model):
    """(settings, evaluator, tau, w) of a calibration whose torque features' range ends at an
    inertial torque of 0.5 N·m: tau the loop's slowest time constant [s], w the weight [-] an
    excess beyond it takes (the larger of the learned, 0, and the default)."""
    learned = dict(zip(BOUND_TERMS['torque'], (0.05, 0.0, 0.1, 0.2)))
    settings = replace(FdiSettings(), torque_feature_range=(math.inf, 0.5, 2.0, 1.0),
                       calibrated_slip=0.05, speed_sigma=0.01, **learned)
    tau = slowest_time_constant(model.dynamics, model.drive.torque_per_amp, model.firmware)
    weight = max(learned['torque_inertia_fraction'], bound_weights(PRIOR_SETTINGS, 'torque')[1])
    return settings, ResidualEvaluator(model, settings), tau, weight


def test_the_torque_bound_remembers_a_manoeuvre_beyond_calibration_not_a_wheel_alone(model):
    """A row whose inertial torque is X beyond what calibration covered widens the torque bound
    by w X (w: the larger of the learned and the default weight); the rows after it, inside the
    range again, keep w X exp(-(t - t_0) / tau), tau the loop's slowest time constant, the same
    row by row; nothing from before a restart. A row whose wheel speeds fit no rigid motion (one
    wheel stopping dead, a reading frozen) is not remembered: the residual is there to show it;
    unless every wheel moves toward its commanded speed (a commanded turn the wheels slip
    through together); on a base whose speeds always fit one (three wheels) no row is."""
    settings, evaluator, tau, weight = extrapolating(model)
    rows, dt, excess = 12, 0.01, 3.0  # [N·m] of inertial torque beyond the range, on wheel 2
    stamp = 50.0 + dt * np.arange(rows)
    features = np.tile([1.0, 0.2, 0.5, 0.5], (rows, 4, 1))
    features[0, 2, 1] = 0.5 + excess
    beyond = evaluator.bound_parts('torque', features)[1]
    assert beyond[0, 2] == pytest.approx(weight * excess) and np.all(np.delete(beyond.ravel(), 2) == 0.0)
    motion = np.tile(model.kinematics.inverse(np.array([0.8, -0.5, 2.0])), (rows, 1))  # fits
    null = np.linalg.svd(model.kinematics.jacobian.T)[2][-1]
    unfit = motion.copy()
    unfit[0] += 0.5 * null / np.abs(null).max()  # the row beyond the range fits no motion
    assert evaluator.fit_a_motion(motion).all() and evaluator.fit_a_motion(unfit).tolist() == [False] + [True] * (rows - 1)
    fresh = np.zeros(rows, dtype=bool)
    added = evaluator._remembered_torque_extrapolation(beyond, motion, stamp, fresh, lambda: fresh)
    expected = np.zeros((rows, 4))
    expected[1:, 2] = weight * excess * np.exp(-(stamp[1:] - stamp[0]) / tau)
    np.testing.assert_allclose(added, expected, rtol=1e-9, atol=1e-12)
    one_by_one = ResidualEvaluator(model, settings)
    by_row = np.concatenate([one_by_one._remembered_torque_extrapolation(
        beyond[k:k + 1], motion[k:k + 1], stamp[k:k + 1], fresh[k:k + 1], lambda: fresh[:1])
        for k in range(rows)])
    np.testing.assert_array_equal(by_row, added)
    restart = fresh.copy()
    restart[4] = True
    after = ResidualEvaluator(model, settings)._remembered_torque_extrapolation(
        beyond, motion, stamp, restart, lambda: fresh)
    np.testing.assert_allclose(after[:4], expected[:4], rtol=1e-9, atol=1e-12)
    assert np.all(after[4:] == 0.0)
    alone = ResidualEvaluator(model, settings)._remembered_torque_extrapolation(beyond, unfit, stamp,
                                                                               fresh, lambda: fresh)
    assert np.all(alone == 0.0)
    followed = np.ones(rows, dtype=bool)  # every wheel moving toward its command: a turn slipped through
    turned = ResidualEvaluator(model, settings)._remembered_torque_extrapolation(
        beyond, unfit, stamp, fresh, lambda: followed)
    np.testing.assert_allclose(turned, expected, rtol=1e-9, atol=1e-12)
    # no calibrated slip, or three wheels (which always fit a motion): no row shows a manoeuvre
    assert not ResidualEvaluator(model, replace(settings, calibrated_slip=math.inf)).fit_a_motion(motion).any()
    three = ResidualEvaluator(load_model('robotino'), settings)
    assert not three.fit_a_motion(np.zeros((2, 3))).any()


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
    2 rad/s practically not. An exact reading still allows the tanh's own error against the
    step it smooths, F_c (1 - tanh(|w| / v_s)). The shift's scale is the learned bound plus that, times the load
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
    # an exact reading: the tanh's own error against the step it smooths, F_c (1 - tanh(w / v_s))
    exact = dynamics.coulomb_span(np.array([0.0, 0.01, 0.06, 2.0]), 0.0)
    np.testing.assert_allclose(exact, 0.03 * np.array([2.0, 1.0 - math.tanh(0.2), 1.0 - math.tanh(1.2),
                                                       1.0 - math.tanh(40.0)]), rtol=1e-12)
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


def test_a_row_follows_its_commands_where_every_wheel_moves_toward_its_command(model):
    """Velocity mode, every wheel's error to its command smaller than at the sample before or
    within 3 speed_sigma (0.03 rad/s here): a hard turn the wheels follow, one of them holding
    its speed; not where one wheel moves away (blocked) or does not move while its command is
    far (a frozen reading), where a reading is NaN, or in current mode."""
    from youbot_fdi.fdi.residuals import ResidualEvaluator
    evaluator = ResidualEvaluator(model, replace(FdiSettings(), speed_sigma=0.01))
    commanded = np.tile([-1.5, -10.8, 5.0, 3.0], (6, 1))
    before = np.tile([8.6, 8.6, 5.0, 3.0], (6, 1))
    now = np.tile([5.0, 2.0, 5.02, 3.0], (6, 1))  # two wheels on their way, two holding
    now[1, 2] = 5.1  # a holding wheel off by more than the noise, moving away
    now[2, 0] = 8.6  # a reading that does not move (frozen) while its command is far
    now[3, 1] = 9.0  # a wheel moving away from its command
    now[4, 3] = np.nan
    mode = np.array([True, True, True, True, True, False])
    followed = evaluator.follow_commands(now, before, commanded, mode)
    assert followed.tolist() == [True, False, False, False, False, False]
    live = [evaluator.follow_commands(now[k:k + 1], before[k:k + 1], commanded[k:k + 1],
                                      mode[k:k + 1])[0] for k in range(6)]
    assert live == followed.tolist()


def test_the_torque_shift_scale_keeps_what_a_manoeuvre_left_not_the_steady_allowances(model):
    """The torque bound is the learned part + the allowances + what a manoeuvre beyond
    calibration left (w X exp(-t / tau), as above); the shift's scale is the learned part + that
    remembered part (+ the Coulomb span): the allowances for steady biases cancel in a departure
    from the level, a manoeuvre's model error does not."""
    settings, evaluator, tau, weight = extrapolating(model)
    rows, dt, excess = 8, 0.01, 3.0  # [N·m] of inertial torque beyond the range, on wheel 1
    stamp = 50.0 + dt * np.arange(rows)
    features = np.tile([1.0, 0.2, 0.5, 0.5], (rows, 4, 1))
    features[0, 1, 1] = 0.5 + excess
    motion = np.tile(model.kinematics.inverse(np.array([0.8, -0.5, 2.0])), (rows, 1))
    allowance, load = np.full((rows, 4), 0.3), np.full((rows, 1), 1.5)
    none = np.zeros(rows, dtype=bool)
    bound, scale = evaluator._torque_bounds(features, allowance, motion, load, stamp, none,
                                            lambda: none)
    within = 0.05 + 0.1 * 0.5 + 0.2 * 0.5  # sigma + the current change's and friction's terms
    remembered = np.zeros((rows, 4))
    remembered[0, 1] = weight * excess  # the row's own extrapolation
    remembered[1:, 1] = weight * excess * np.exp(-(stamp[1:] - stamp[0]) / tau)
    np.testing.assert_allclose(bound, within + 0.3 + remembered, rtol=1e-9)
    coulomb = 1.5 * model.dynamics.coulomb_span(motion, evaluator._speed_uncertainty)
    np.testing.assert_allclose(scale, within + remembered + coulomb, rtol=1e-9)


def test_a_residual_vector_carries_the_friction_level_and_an_older_one_lacks_it(model):
    """The labelled residual vector (the residual node's message) carries each wheel's friction
    level exactly; a vector from a generator that does not publish it (older) gives frames with
    none, which stand for 0 (the shift's scale widened by nothing); any other label missing is an
    error that names it."""
    from frames import torque_frame
    names, n = model.wheel_names, len(model.wheel_names)
    frame = replace(torque_frame(model, 3.0, 0.5), friction_level=np.array([0.1, 0.2, 0.3, 0.4]))
    labels, values, bounds = frame.to_labelled(names)
    back = ResidualFrame.from_labelled(3.0, labels, values, bounds, names)
    np.testing.assert_array_equal(back.friction_level, [0.1, 0.2, 0.3, 0.4])
    older = [i for i, label in enumerate(labels) if not label.startswith('friction_level_')]
    assert len(older) == len(labels) - n
    before = ResidualFrame.from_labelled(3.0, [labels[i] for i in older], values[older], bounds[older], names)
    assert before.friction_level is None
    np.testing.assert_array_equal(before.signal('friction_level'), np.zeros(n))
    np.testing.assert_array_equal(ResidualBatch.of_frames([before]).friction_level, np.zeros((1, n)))
    np.testing.assert_array_equal(before.values['torque'], frame.values['torque'])
    with pytest.raises(ValueError, match='lacks shift_scale_fl'):
        kept = [i for i, label in enumerate(labels) if label != 'shift_scale_fl']
        ResidualFrame.from_labelled(3.0, [labels[i] for i in kept], values[kept], bounds[kept], names)
