"""``youbot_fdi/fdi/observer.py``: the model observer and the command path (the firmware loop's
prediction, its restart from the measured state), the load factor the wheels share, friction
beyond the calibrated speeds, commands counted late; each against a hand-derived closed form."""
from dataclasses import replace

import numpy as np
import pytest

from youbot_fdi.fdi.learned import mask_wheels
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.model import load_model

FAST_EXCEPT = ()  # `make check`: every test here (the unit tests of the core, under a minute)


@pytest.fixture(scope='module')
def model():
    return load_model('youbot')


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


def test_past_one_wheels_current_every_wheel_takes_its_speed_and_that_wheel_its_integral(model):
    """Where wheel bl's current passes what calibration saw (and on the row after), every wheel's
    prediction is its measured speed (the plant's torques are not the model's there, and through
    the base they move every wheel), but only bl's integral is the one its current implies; the
    others keep their loop's own (a current implies it only through gains and readings
    calibration may have got wrong). After it every wheel predicts. A block gives the rows one
    by one gave."""
    from youbot_fdi.fdi.observer import CALIBRATED_SHARE, ModelObserver
    from youbot_fdi.samples import CommandSample, JointBatch, JointSample
    settings = replace(FdiSettings(), calibrated_effort=1.0)
    signs = model.kinematics.drive_signs
    speeds = np.array([1.0, 1.5, 2.0, 2.5])
    stamps = [0.01, 0.02, 0.03, 0.04]
    low = np.full(4, 0.1)
    high = low.copy()
    high[2] = CALIBRATED_SHARE * settings.calibrated_effort + 0.5
    efforts = [low, high, low, low]

    def observer():
        made = ModelObserver(model, settings)
        made.command(CommandSample(0.0, 'velocity', np.full(4, 5.0)))
        return made

    past, plain = observer(), observer()
    rows, n = [], 4
    for k, stamp in enumerate(stamps):
        sample = JointSample(stamp, np.zeros(4), signs * (speeds + 0.1 * k), signs * efforts[k])
        rows.append(past.update(sample))
        if k < 2:
            plain.update(JointSample(stamp, np.zeros(4), sample.velocity, signs * low))
        if k == 1:
            integrals, own_integrals = past._command_state[n:].copy(), plain._command_state[n:]
            implied = past._start_integral(high[None], (speeds + 0.1)[None], np.array([True]),
                                           (signs * 5.0)[None])[0]  # the command, kinematic
    np.testing.assert_allclose(rows[1].from_commands, speeds + 0.1)  # every measured speed
    others = [0, 1, 3]
    np.testing.assert_allclose(integrals[others], own_integrals[others], rtol=1e-12)
    assert integrals[2] == pytest.approx(implied[2]) and abs(integrals[2] - own_integrals[2]) > 1e-3
    np.testing.assert_allclose(rows[2].from_commands, speeds + 0.2)  # the row after
    assert np.all(np.abs(rows[3].from_commands - (speeds + 0.3)) > 1e-6)  # predicting again
    assert list(mask_wheels(rows[1].resynced, 4)) == [False, False, True, False]
    block = observer().update_batch(JointBatch(
        np.array(stamps), np.zeros((4, 4)), np.array([signs * (speeds + 0.1 * k) for k in range(4)]),
        np.array([signs * e for e in efforts])))
    np.testing.assert_allclose(block.from_commands[1:], [row.from_commands for row in rows[1:]],
                               rtol=1e-12)  # the first row restarts: live, no prediction


@pytest.mark.parametrize('others_saturate', [False, True])
def test_a_row_past_one_wheels_current_runs_it_at_its_limit_unless_another_wheels_limit_acts(
        model, others_saturate):
    """While wheel bl stays past its current at its limit (a stuck wheel holds it there), every
    row takes the measured speeds and bl's implied integral, so only the other wheels'
    integrals come from the row's step. Where only bl's loop starts the row at its limit (bl 6
    rad/s from its command, the others on theirs), bl runs the row at that current (the model's
    wheel past calibration is not the plant's: a stuck wheel's current stays at its limit where
    the model's loop would let it go), the others' loops as the firmware runs them: checked
    against the loop stepped period by period by hand; bl's own loop stepped instead gives
    other integrals. Where the others' limits act too (a command 49 rad/s beyond their speeds),
    the row is stepped period by period, and the firmware's anti-windup holds their integrals at
    ``max_current / ki`` [rad] with the error's sign (a linear step winds 0.5 rad a row, past
    the limit of 0.405 rad). A block gives the rows one by one gave."""
    from youbot_fdi.fdi.observer import CALIBRATED_SHARE, ModelObserver
    from youbot_fdi.samples import CommandSample, JointBatch, JointSample
    settings = replace(FdiSettings(), calibrated_effort=1.0)
    signs = model.kinematics.drive_signs
    command = 50.0 if others_saturate else 1.0  # [rad/s], every wheel
    speeds, rows, n, others = signs * 1.0, 6, 4, [0, 1, 3]  # kinematic
    speeds[2] -= 6.0  # bl 6 rad/s off: kp times that is past the current limit
    stamps = 0.01 * (1 + np.arange(rows))  # 10 firmware periods a row
    efforts = np.full((rows, 4), 0.1)
    efforts[1:, 2] = ModelObserver(model, settings).max_torque  # bl at its limit, from row 1
    assert efforts[1, 2] >= CALIBRATED_SHARE * settings.calibrated_effort  # past what it saw

    def observer():
        made = ModelObserver(model, settings)
        made.command(CommandSample(0.0, 'velocity', np.full(4, command)))
        return made

    live, states = observer(), []
    for stamp, effort in zip(stamps, efforts):
        live.update(JointSample(stamp, np.zeros(4), signs * speeds, signs * effort))
        states.append(live._command_state.copy())
    target, limit, top = signs * command, live._integral_limit, live.max_current  # kinematic
    if others_saturate:
        error = target - speeds
        np.testing.assert_array_equal(states[-1][n:][others], np.sign(error[others]) * limit)
    else:
        phi, gamma = live._phi1, live._gamma1 * live.torque_per_amp  # one period; no Coulomb
        for k in range(2, rows):  # the rows that start with bl at its limit
            speed, integral = states[k - 1][:n].copy(), states[k - 1][n:].copy()
            at_limit = np.sign(live.kp * (target[2] - speed[2])) * top
            for _ in range(10):
                error = target - speed
                integral = integral + error * live.period
                current = live.kp * error + live.ki * integral
                assert np.all(np.abs(current[others]) < top)  # the others' loops stay linear
                current[2] = at_limit
                speed = phi @ speed + gamma @ current
            np.testing.assert_allclose(states[k][n:][others], integral[others], rtol=1e-9)
            stepped, _ = live._stepped(states[k - 1], 10, target, np.zeros(4))  # bl's own loop
            assert np.abs(stepped[n:][others] - integral[others]).max() > 1e-7
    block = observer()
    block.update_batch(JointBatch(stamps, np.zeros((rows, 4)), np.tile(signs * speeds, (rows, 1)),
                                  signs * efforts))
    np.testing.assert_allclose(block._command_state, live._command_state, rtol=1e-12)


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
    assert not judged[0.3].any() and not judged[0.31].any()  # every wheel took its measured speed
    assert judged[0.29].all() or integral_gain is not None  # a slow loop still settles from its start
    # settling: after the row after the jump (0.31 s), for bl alone
    for j in range(1, int(settle / 0.01) - 1):
        now = judged[round(0.31 + 0.01 * j, 2)]
        assert not now[2]
        assert now[[0, 1, 3]].all() or 0.01 * (31 + j) < 0.01 + settle  # the start (0.01 s) settling
    after = round(0.31 + 0.01 * (int(settle / 0.01) + 2), 2)
    assert judged[after].all()


def test_the_load_factor_follows_a_platform_change_of_any_size(model):
    """No clamp: every wheel needing about three times its friction is a factor of about 3 (the
    median); one wheel alone cannot move it; most wheels changing alike while one does not (a
    floor that triples rolling friction and leaves a sliding wheel's) is most wheels' change."""
    from youbot_fdi.fdi.observer import ModelObserver
    observer = ModelObserver(model, FdiSettings())
    friction = np.full(4, 0.2)

    def factor(ratios, previous=1.0, voting=(True,) * 4):
        votes = np.where(voting, friction, 0.0)
        row = np.concatenate([np.array(ratios) * votes, votes, 0.0 * votes])[None]  # all Coulomb
        return float(observer._load_factor(row, previous, np.ones((1, 4)))[0][0])

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
            np.concatenate([np.array(ratios + [0.0, 0.0]) * friction, friction, 0.0 * friction])[None],
            previous, np.ones((1, 4)))[0][0])

    assert factor([2.1, 1.8], 1.0) == pytest.approx(1.8)  # both: the smaller change
    assert factor([0.6, 0.7], 1.0) == pytest.approx(0.7)
    assert factor([5.0, 1.05], 1.0) == pytest.approx(1.05)  # one wheel's fault: the other's
    assert factor([5.0, 0.95], 1.0) == pytest.approx(1.0)  # either side of the last: held
    assert factor([0.3, 1.0], 1.7) == pytest.approx(1.0)
    one = np.concatenate([[0.6, 0.0, 0.0, 0.0], [0.2, 0.0, 0.0, 0.0], np.zeros(4)])[None]  # one voter at x3
    assert float(observer._load_factor(one, 1.7, np.ones((1, 4)))[0][0]) == pytest.approx(1.7)  # held


def test_a_wheel_reversing_weighs_its_ratios_by_their_friction_levels_not_their_signs(model):
    """Closed form: a wheel reading 1.0 of its level -0.4 N·m, then, reversed, 1.2 of +0.3 N·m,
    the smoothing keeping half of the past: its smoothed ratio is the level-weighted mean,
    (0.5 x 0.5 x 0.4 x 1.0 + 0.5 x 0.3 x 1.2) / (0.5 x 0.5 x 0.4 + 0.5 x 0.3) = 0.28 / 0.25 =
    1.12, between the two. Summed with their signs the levels nearly cancel (0.05 N·m) and the
    ratio is 0.08 / 0.05 = 1.6, beyond both (the randomized suite's seed 15, plant 88: wheels
    reversing under a heavy payload read -0.01 and 0.06, and a factor of 0.06 took nearly all
    friction out of the model)."""
    from youbot_fdi.fdi.observer import ModelObserver
    from youbot_fdi.fdi.recursions import scalar_recursion
    observer = ModelObserver(model, FdiSettings())
    level = np.array([[-0.4] * 4, [0.3] * 4])
    torque = np.array([[1.0], [1.2]]) * level  # steady: the explained torque is the level
    votes = np.concatenate(observer._load_votes(torque, level, level, 0.0 * level, None), axis=1)
    keep = np.full(2, 0.5)
    smoothed = scalar_recursion(keep, (1.0 - keep)[:, None] * votes, np.zeros(12))
    factor = observer._load_factor(smoothed, 1.0, np.ones((2, 4)))[0]
    np.testing.assert_allclose(factor, [1.0, 1.12], rtol=1e-12)


def test_the_load_spread_is_how_far_the_other_wheels_stand_from_the_factor():
    """Per wheel, the median over the other voting wheels of |ratio - factor|: a wheel's own
    fault leaves its spread as the others make it; one faulty wheel among three others moves
    their median little; no other voter, no spread."""
    from youbot_fdi.fdi.observer import load_spread
    nan = np.nan
    ratio = np.array([[5.0, 1.1, 0.9, 1.0],  # wheel 0 faulty, the factor 1.0
                      [1.65, nan, nan, 0.83],  # two voters (a floor each wheel meets its own way)
                      [1.2, nan, nan, nan]])  # one voter
    factor = np.array([1.0, 1.09, 1.2])
    # |ratio - factor|: (4, 0.1, 0.1, 0); (0.56, -, -, 0.26); (0, -, -, -)
    expected = np.array([[0.1, 0.1, 0.1, 0.1],  # medians of (0.1, 0.1, 0), (4, 0.1, 0), ...
                         [0.26, 0.41, 0.41, 0.56],  # a wheel that does not vote is judged too
                         [0.0, 0.0, 0.0, 0.0]])
    np.testing.assert_allclose(load_spread(ratio, factor), expected, atol=1e-12)
    np.testing.assert_allclose(load_spread(ratio[:1], factor[:1]), expected[:1], atol=1e-12)  # a live row


def test_a_wheel_its_rollers_may_turn_more_than_its_friction_does_not_vote_on_the_load():
    """Closed form (the randomized suite's seed 6, plant 198): a diagonal drive, two wheels
    rolling at 12.6 rad/s and two creeping at 0.03 rad/s whose rollers glide (pattern
    cos(pi/4)). With F_c = 0.1 N·m the creeping wheels' friction levels (F_c tanh(0.03 / v_s) +
    b 0.03 = 0.055 N·m) are below the drag their rollers may pass (F_c cos(pi/4) tanh(glide /
    v_s) = 0.071 N·m), the rolling ones' (0.54 N·m) far above it. Turned by their rollers, the
    creeping wheels hold -1.2 and -1.4 times their levels and do not vote: the factor is what
    the rolling wheels' 1.1 and 1.2 say with the value before (two voters: clip(1, 1.1, 1.2) =
    1.1). Counted as votes (no pattern given), the median of the four is below zero: 0."""
    from youbot_fdi.fdi.observer import coulomb_share, ModelObserver
    from youbot_fdi.model.profile import PlatformModel
    base = load_model('youbot')
    coulomb = PlatformModel(replace(base.profile, dynamics=replace(
        base.profile.dynamics, coulomb_friction=(0.1,) * 4)))
    dyn = coulomb.dynamics
    velocity = coulomb.kinematics.inverse(np.array([0.3, 0.3, 0.0]))
    creeping = np.abs(velocity) < 1e-9
    velocity = np.where(creeping, 0.03, velocity)[None]
    viscous = np.diag(dyn.friction_matrix) * velocity
    level = viscous + dyn.coulomb_level(velocity)
    shape = dyn.roller_drag_shape(velocity)
    rollers = np.abs(dyn.coulomb * shape)[0]
    assert creeping.sum() == 2 and (rollers[creeping] > level[0, creeping]).all()
    assert (rollers[~creeping] < level[0, ~creeping]).all()
    ratio = np.where(creeping, [-1.2, 0.0, 0.0, -1.4], [0.0, 1.1, 1.2, 0.0])
    torque = ratio * level  # steady: the explained torque is the level
    observer = ModelObserver(coulomb, FdiSettings())
    share = coulomb_share(viscous, level)
    load, friction, _ = votes = observer._load_votes(torque, level, level, viscous, shape)
    np.testing.assert_array_equal(load[0], np.where(creeping, 0.0, torque[0]))
    np.testing.assert_array_equal(friction[0], np.where(creeping, 0.0, level[0]))
    factor, _ = observer._load_factor(np.concatenate(votes, axis=1), 1.0, share)
    assert factor[0] == pytest.approx(1.1)
    every = observer._load_votes(torque, level, level, viscous, None)
    assert observer._load_factor(np.concatenate(every, axis=1), 1.0, share)[0][0] == 0.0


def test_the_drag_spread_is_how_far_the_other_gliding_wheels_stand_from_the_shared_drag(model):
    """Sideways, every youBot roller glides (pattern +-cos 45 deg): wheels whose residuals read
    drags of 0.3, 0.1, 0.12 and 0.08 N·m per unit pattern share the median, 0.11, and each may
    stand off it by the median of the *other* wheels' distances from it, times its pattern:
    wheel 0 (the outlier, a fault's place) by 0.01 (its neighbours agree), wheels 1 and 2 by
    0.03, wheel 3 by 0.01. Creeping after it (the rollers glide too slowly to vote), the faded
    voters' spread stands, times the smaller pattern, alike one row at a time (the live path)
    and in a block; once they have faded, no spread."""
    from youbot_fdi.fdi.observer import ModelObserver
    velocity = model.kinematics.inverse(np.array([0.0, 0.3, 0.0]))[None]
    creeping = 0.002 * velocity
    ratios = np.array([0.3, 0.1, 0.12, 0.08])
    spread = np.array([[0.01, 0.03, 0.03, 0.01]])

    def drag(observer, speed, residual, keep):
        quiet = np.zeros_like(speed)  # steady: no inertial torque, friction 1 N·m
        return observer._shared_drag(speed, model.dynamics.roller_drag_shape(speed), residual,
                                     quiet, quiet + 1.0, np.array(keep))

    shape, slow = (model.dynamics.roller_drag_shape(v) for v in (velocity, creeping))
    np.testing.assert_allclose(np.abs(shape), np.cos(np.pi / 4), rtol=1e-6)  # every roller glides
    assert (np.abs(slow) > 0.0).all() and (np.abs(slow) < 0.5 * np.abs(shape)).all()  # no vote
    observer = ModelObserver(model, FdiSettings())
    torque, allowed = drag(observer, velocity, ratios * shape, [0.0])
    np.testing.assert_allclose(torque, 0.11 * shape, rtol=1e-9)
    np.testing.assert_allclose(allowed, spread * np.abs(shape), rtol=1e-9)
    # creeping, the smoothing keeping half of the voters' sums: their ratios, the drag held
    by_row = drag(observer, creeping, 0.0 * creeping, [0.5])
    np.testing.assert_allclose(by_row[0], 0.11 * slow, rtol=1e-9)
    np.testing.assert_allclose(by_row[1], spread * np.abs(slow), rtol=1e-9)
    by_block = drag(ModelObserver(model, FdiSettings()), np.concatenate([velocity, creeping]),
                    np.concatenate([ratios * shape, 0.0 * creeping]),
                    [0.0, 0.5])
    for row, block in zip(by_row, by_block):
        np.testing.assert_allclose(row, block[1:], atol=1e-12)
    np.testing.assert_allclose(drag(observer, creeping, 0.0 * creeping, [1e-6])[1], 0.0)  # faded


def test_a_shared_change_is_the_coulomb_parts_so_a_wheel_split_otherwise_may_stand_off_it():
    """Closed forms of split_spread: voters whose friction was a quarter Coulomb read a factor of
    2, so their Coulomb part rose fivefold (1 + 1 / 0.25), the viscous part the same: a wheel
    with three quarters more Coulomb share than any of them may stand 0.75 x 4 = 3 off the
    factor. A factor below 1 past what the Coulomb part alone can give (0.69 from a fifth: the
    Coulomb part at 0, the viscous at 0.69 / 0.8) gives |0 - 0.8625| per unit share. No change,
    no share beyond the others', or an unknown share: nothing; voters without a Coulomb part
    cannot tell its rise: nothing either (no bound without end)."""
    from youbot_fdi.fdi.observer import split_spread
    factor = np.array([2.0, 0.69, 1.0, 2.0, 1.5])
    voters = np.array([0.25, 0.2, 0.25, 0.25, 0.0])
    beyond = np.array([[0.75, 0.0], [0.8, 0.5], [0.75, 0.0], [np.nan, 0.5], [0.5, 0.0]])
    expected = np.array([[3.0, 0.0], [0.69, 0.43125], [0.0, 0.0], [0.0, 2.0], [0.0, 0.0]])
    np.testing.assert_allclose(split_spread(factor, voters, beyond), expected, rtol=1e-12)
    np.testing.assert_allclose(split_spread(factor[:1], voters[:1], beyond[:1]), expected[:1])  # a live row


def test_a_wheels_share_beyond_the_others_is_its_distance_outside_their_span():
    """Per wheel, how far its Coulomb share now stands outside the other voting wheels' shares:
    0 inside their span, where no other wheel votes, or where its own share is unknown."""
    from youbot_fdi.fdi.observer import beyond_the_others, coulomb_share
    nan = np.nan
    shares = np.array([[0.2, 0.3, 0.25, nan], [0.5, nan, nan, nan]])
    share = np.array([[0.9, 0.1, 0.25, 0.35], [0.9, 0.1, nan, 0.5]])
    expected = np.array([[0.6, 0.1, 0.0, 0.05], [0.0, 0.4, 0.0, 0.0]])
    np.testing.assert_allclose(beyond_the_others(shares, share), expected, atol=1e-12)
    np.testing.assert_allclose(coulomb_share(np.array([0.15, 0.3, 0.1, -0.1]), np.array([0.2, 0.2, 0.0, 0.2])),
                               [0.25, 0.0, nan, 1.0])


def test_a_slow_wheel_beside_fast_ones_on_a_new_floor_may_need_more_than_the_factor(model):
    """The observer's load spread of a wheel (``_load_factor``) is the larger of the other
    voters' spread and the split: three fast wheels, a quarter Coulomb, read 2 (their Coulomb
    part fivefold); a fourth wheel standing still votes not, and creeping now (all Coulomb) may
    stand 0.75 x 4 = 3 off; at the fast wheels' share it may stand only as far as they do."""
    from youbot_fdi.fdi.observer import ModelObserver
    observer = ModelObserver(model, FdiSettings())
    friction = np.array([0.2, 0.2, 0.2, 0.0])
    row = np.concatenate([2.0 * friction, friction, 0.75 * friction])[None]
    _, spread = observer._load_factor(row, 1.0, np.array([[0.25, 0.25, 0.25, 1.0]]))
    np.testing.assert_allclose(spread, [[0.0, 0.0, 0.0, 3.0]], atol=1e-12)
    _, spread = observer._load_factor(row, 1.0, np.full((1, 4), 0.25))
    np.testing.assert_allclose(spread, [[0.0, 0.0, 0.0, 0.0]], atol=1e-12)


def test_the_torque_bound_allows_the_larger_of_the_configured_share_and_the_spread(model):
    """The torque allowance is max(load_allowance |L - 1|, spread) x |friction| (+ the unseen
    friction at the load): a floor the other wheels meet each their own way widens it."""
    from youbot_fdi.fdi.residuals import ResidualEvaluator
    evaluator = ResidualEvaluator(model, FdiSettings())
    zero = np.zeros((1, 4))
    friction = np.array([[0.2, -0.2, 0.1, 0.0]])
    spread = np.array([[0.0, 0.56, 0.2, 3.0]])
    load = np.array([[1.6]])
    _, _, allowance = evaluator._torque_terms(zero, zero, zero, zero, zero, friction, zero, load,
                                              spread, np.array([[0.01]]))
    share = np.maximum(FdiSettings().load_allowance * 0.6, spread)  # 0.3 configured
    np.testing.assert_allclose(allowance, share * np.abs(friction), atol=1e-12)
    assert allowance[0, 1] == pytest.approx(0.56 * 0.2)


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


def test_where_calibration_told_the_slope_its_error_times_the_distance_bounds_the_extrapolation(model):
    """Calibrated at 6 rad/s (the norm) with a viscous slope known to 0.005 N·m·s/rad: at twice
    the speed each wheel turns 3 rad/s beyond its calibrated point, so the fit may be off by
    2 x 0.005 x 3 = 0.03 N·m, less than the friction there that lies between the all-Coulomb and
    all-viscous extrapolations; a slope known to 0.5 keeps that, and a wheel without a stated
    deviation too."""
    from dataclasses import replace as replaced
    from youbot_fdi.fdi.observer import FRICTION_INTERVAL_SD, ModelObserver
    from youbot_fdi.model.profile import PlatformModel
    assert FRICTION_INTERVAL_SD == 2.0  # the closed form below takes two
    direction = np.array([1.0, -1.0, 1.0, -1.0]) / 2.0  # unit norm
    settings = replace(FdiSettings(), calibrated_speed_range=(6.0, 6.0))
    fast = direction * 12.0

    def observer(viscous_sd):
        stated = {f'viscous_friction[{w}]': sd for w, sd in enumerate(viscous_sd) if sd}
        return ModelObserver(PlatformModel(replaced(model.profile, identification={'uncertainty': stated})),
                             settings)

    between = ModelObserver(model, settings)._speed_extrapolation(fast)
    assert np.all(between > 0.03)
    np.testing.assert_allclose(observer([0.005] * 3 + [0.0])._speed_extrapolation(fast),
                               [0.03, 0.03, 0.03, between[3]])
    np.testing.assert_allclose(observer([0.5] * 4)._speed_extrapolation(fast), between)


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


def test_a_wheels_coulomb_share_spans_what_its_identified_levels_allow(model):
    """``_share_interval``: at 2 rad/s (the Coulomb level saturated) a wheel of F_c = 0.05 +- 0.02
    N·m and viscous 0.035 +- 0.01 N·m·s/rad has the share 0.05 / 0.12; two standard deviations
    each way, the parts moving apart: (0.05 - 0.04) / (0.01 + 0.055 x 2) = 1/12 and
    (0.05 + 0.04) / (0.09 + 0.015 x 2) = 3/4. A wheel without a stated uncertainty, and a model
    without an identification, keep the point."""
    from dataclasses import replace as replaced
    from youbot_fdi.fdi.observer import ModelObserver, FRICTION_INTERVAL_SD
    from youbot_fdi.model.profile import PlatformModel
    assert FRICTION_INTERVAL_SD == 2.0  # the closed forms below take two
    stated = {f'{name}[{w}]': sd for w in range(3)
              for name, sd in (('coulomb_friction', 0.02), ('viscous_friction', 0.01))}
    profile = replaced(model.profile, dynamics=replaced(model.profile.dynamics, coulomb_friction=(0.05,) * 4),
                       identification={'uncertainty': stated})
    observer = ModelObserver(PlatformModel(profile), FdiSettings())
    speed = np.array([[2.0, -2.0, 2.0, 2.0]])
    viscous = observer.friction * speed
    friction = viscous + 0.05 * np.sign(speed)
    low, high = observer._share_interval(speed, viscous, friction)
    point = 0.05 / 0.12
    np.testing.assert_allclose(low, [[1 / 12, 1 / 12, 1 / 12, point]], rtol=1e-9)
    np.testing.assert_allclose(high, [[0.75, 0.75, 0.75, point]], rtol=1e-9)
    bare = ModelObserver(PlatformModel(replaced(profile, identification=None)), FdiSettings())
    low, high = bare._share_interval(speed, viscous, friction)
    np.testing.assert_allclose(low, np.full((1, 4), point))
    np.testing.assert_allclose(high, low)


def test_a_wheel_whose_split_calibration_could_not_tell_may_stand_off_a_new_floor_by_it(model):
    """``_load_factor`` with share intervals: voters a quarter Coulomb read 2 (their Coulomb part
    fivefold, gap 4); a wheel of share 0.25 whose identified levels allow up to 0.75 may stand
    0.5 x 4 = 2 off the factor, one allowed down to 0.1 (0.15 below them) 0.6; on the calibrated
    floor (every ratio 1) the interval allows nothing."""
    from youbot_fdi.fdi.observer import ModelObserver
    observer = ModelObserver(model, FdiSettings())
    friction = np.array([0.2, 0.2, 0.2, 0.0])
    row = np.concatenate([2.0 * friction, friction, 0.75 * friction])[None]
    share = np.full((1, 4), 0.25)
    _, spread = observer._load_factor(row, 1.0, share, np.array([[0.25, 0.25, 0.25, 0.75]]))
    np.testing.assert_allclose(spread, [[0.0, 0.0, 0.0, 2.0]], atol=1e-12)
    _, spread = observer._load_factor(row, 1.0, np.array([[0.25, 0.25, 0.25, 0.1]]), share)
    np.testing.assert_allclose(spread, [[0.0, 0.0, 0.0, 0.6]], atol=1e-12)
    calibrated = np.concatenate([friction, friction, 0.75 * friction])[None]
    _, spread = observer._load_factor(calibrated, 1.0, share, np.array([[0.25, 0.25, 0.25, 0.75]]))
    np.testing.assert_allclose(spread, np.zeros((1, 4)), atol=1e-12)
