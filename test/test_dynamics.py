"""Mass matrix against the report's closed form; exact discretisation against scipy and closed forms."""
import math
import numpy as np
import pytest
import scipy.signal

from youbot_fdi.model import DriveTrain, load_model, zoh_discretize

pytestmark = pytest.mark.fast  # `make check`: the unit tests of the core, under a minute

R, K = 0.0475, 0.385


@pytest.fixture(scope='module', params=['seed', 'youbot'])
def model(request):
    return load_model(request.param)


def report_mass_matrix(m, j_z, j_w):
    """Report §3.2: M with A = m R^2 / 8, B = J_z R^2 / (16 (l+L)^2)."""
    a, b = m * R ** 2 / 8, j_z * R ** 2 / (16 * K ** 2)
    return np.array([[a + b + j_w, -b, b, a - b], [-b, a + b + j_w, a - b, b],
                     [b, a - b, a + b + j_w, -b], [a - b, b, -b, a + b + j_w]])


def test_mass_matrix_equals_report_closed_form(model):
    params = model.profile.dynamics
    expected = report_mass_matrix(params.mass, params.yaw_inertia, params.wheel_inertia[0])
    np.testing.assert_allclose(model.dynamics.mass_matrix, expected, rtol=1e-10, atol=1e-15)
    assert np.all(np.linalg.eigvalsh(model.dynamics.mass_matrix) > 0)


def test_seed_profile_has_the_reports_stiffness():
    dyn = load_model('seed').dynamics
    assert 9e3 < np.linalg.cond(dyn.mass_matrix) < 1.1e4
    fastest = dyn.time_constants()[:2]
    assert np.all((fastest > 35e-6) & (fastest < 45e-6))


def test_youbot_profile_is_well_conditioned():
    dyn = load_model('youbot').dynamics
    assert np.linalg.cond(dyn.mass_matrix) < 10
    assert dyn.time_constants()[0] > 0.1  # no sub-millisecond modes


@pytest.mark.parametrize('dt', [1e-4, 1e-3, 1e-2])
def test_zoh_matches_scipy_cont2discrete(model, dt):
    a_matrix, b_matrix = model.dynamics.state_space()
    a_d, b_d = zoh_discretize(a_matrix, b_matrix, dt)
    n = a_matrix.shape[0]
    ref = scipy.signal.cont2discrete((a_matrix, b_matrix, np.eye(n), np.zeros_like(b_matrix)), dt,
                                     method='zoh')
    np.testing.assert_allclose(a_d, ref[0], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(b_d, ref[1], rtol=1e-9, atol=1e-12)


def modal_velocity_step(dyn, velocity, torque, dt):
    """Closed-form exact step of M v' = tau - D v via the generalised eigenvectors (M-orthonormal)."""
    import scipy.linalg
    rates, vectors = scipy.linalg.eigh(dyn.friction_matrix, dyn.mass_matrix)
    q0, u = vectors.T @ dyn.mass_matrix @ velocity, vectors.T @ torque
    decay = np.exp(-rates * dt)
    return vectors @ (decay * q0 + (1 - decay) / rates * u)


@pytest.mark.parametrize('dt', [1e-3, 1e-2])
def test_discrete_model_is_exact_and_stable_with_stiff_seed_values(dt):
    dyn = load_model('seed').dynamics
    discrete = dyn.discretize(dt)
    velocity, torque = np.array([1.0, -2.0, 0.5, 3.0]), np.array([0.1, 0.0, -0.05, 0.02])
    _, new_velocity = discrete.step(np.zeros(4), velocity, torque)
    np.testing.assert_allclose(new_velocity, modal_velocity_step(dyn, velocity, torque, dt),
                               rtol=1e-7, atol=1e-9)
    assert np.max(np.abs(np.linalg.eigvals(discrete.a_d))) <= 1.0 + 1e-12
    # Forward Euler at the same step is violently unstable on these values.
    a_matrix, _ = dyn.state_space()
    euler = np.eye(8) + a_matrix * dt
    assert np.max(np.abs(np.linalg.eigvals(euler))) > 10


def test_constant_torque_settles_at_torque_over_friction(model):
    """M v' = tau - D v: with the same D on every wheel the steady state is tau / D, whatever M."""
    dyn = model.dynamics
    discrete = dyn.discretize(0.01)
    torque = np.array([0.05, -0.02, 0.03, 0.01])
    position, velocity = np.zeros(4), np.zeros(4)
    for _ in range(1000):  # 10 s, many times the slowest time constant
        position, velocity = discrete.step(position, velocity, torque)
    np.testing.assert_allclose(velocity, torque / 0.035, rtol=1e-4)


def test_position_integrates_velocity(model):
    discrete = model.dynamics.discretize(1e-3)
    velocity = np.array([2.0, -1.0, 0.5, 0.0])
    no_friction_torque = model.dynamics.friction_matrix @ velocity  # holds the speeds constant
    position, new_velocity = discrete.step(np.zeros(4), velocity, no_friction_torque)
    np.testing.assert_allclose(new_velocity, velocity, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(position, velocity * 1e-3, rtol=1e-9, atol=1e-15)


def test_current_torque_and_motor_units_round_trip():
    drive = DriveTrain(gear_ratio=364 / 9405, torque_constant=0.0335,
                       encoder_ticks_per_revolution=4000, max_current=3.564)
    assert drive.current_to_torque(1.0) == pytest.approx(0.0335 / (364 / 9405))
    assert drive.milliamps_to_torque(1000.0) == pytest.approx(0.8656, rel=1e-3)
    assert drive.rpm_to_wheel_speed(4000.0) == pytest.approx(16.21, rel=1e-3)
    assert drive.wheel_angle_to_ticks(2 * np.pi) == pytest.approx(4000 / (364 / 9405))
    for value in (-3.0, 0.0, 2.5):
        assert drive.torque_to_current(drive.current_to_torque(value)) == pytest.approx(value)
        assert drive.ticks_to_wheel_angle(drive.wheel_angle_to_ticks(value)) == pytest.approx(value)
        assert drive.wheel_speed_to_rpm(drive.rpm_to_wheel_speed(value)) == pytest.approx(value)
    with pytest.raises(ValueError, match='dt'):
        zoh_discretize(np.zeros((2, 2)), np.zeros((2, 1)), 0.0)


# ---------------------------------------------------------------------- the contact friction law
def _with_dynamics(model, **values):
    """``model`` with its dynamics parameters ``values`` replaced."""
    from dataclasses import replace
    from youbot_fdi.model.profile import PlatformModel
    return PlatformModel(replace(model.profile, dynamics=replace(model.profile.dynamics, **values)))


def _with_ratio(model, ratio):
    return _with_dynamics(model, roller_friction_ratio=ratio)


def test_roller_slide_is_zero_for_a_rolling_contact_and_grows_with_its_angle():
    """Robotino (omni, rollers at 90°): driving along wheel 2's rolling direction (y) its contact
    only rolls; wheels 1 and 3 meet that motion at 30° from their axles, so they slide
    tan(60°) times as fast as they turn."""
    kinematics = load_model('robotino').kinematics
    speeds = kinematics.inverse([0.0, 0.1, 0.0])
    slide = kinematics.roller_slide(speeds)
    assert abs(slide[1]) < 1e-12
    assert np.allclose(np.abs(slide[[0, 2]]) / np.abs(speeds[[0, 2]]), np.tan(np.radians(60.0)))


def test_contact_law_reduces_to_per_wheel_coulomb_without_a_ratio_and_shares_it_with_one():
    base = load_model('robotino')
    speeds = base.kinematics.inverse([0.1, 0.05, 0.2])
    per_wheel = base.dynamics.coulomb * np.tanh(speeds / base.dynamics.parameters.coulomb_velocity_scale)
    assert np.array_equal(base.dynamics.coulomb_torque(speeds), per_wheel)
    contact = _with_ratio(base, 1.0).dynamics
    # k = 1: isotropic contact friction, the motor feels the rolling share of the contact speed
    slide = base.kinematics.roller_slide(speeds)
    share = np.abs(speeds) / np.hypot(speeds, slide)
    assert np.allclose(contact.coulomb_torque(speeds), per_wheel * share)
    batch = np.stack([speeds, 2.0 * speeds, np.zeros(3)])
    assert np.allclose(contact.coulomb_torque(batch)[1], per_wheel * share * np.tanh(
        2 * speeds / 0.2) / np.tanh(speeds / 0.2))
    assert np.array_equal(contact.coulomb_torque(batch)[2], np.zeros(3))


@pytest.mark.parametrize('ratio', [0.0, 0.5])
def test_identify_finds_the_roller_friction_ratio_of_a_drive(ratio):
    """Torques made by the contact law with ratio k on a drive in six directions: the fit's grid
    returns k (and 0 for per-wheel Coulomb friction)."""
    from dataclasses import replace
    from youbot_fdi.fdi.identify import fit_dynamics, RecordingArrays
    from youbot_fdi.model.profile import PlatformModel
    base = load_model('robotino')
    signed = PlatformModel(replace(base.profile, drive=replace(base.drive, signed_effort=True)))
    truth = _with_ratio(signed, ratio)
    dt, segment = 0.01, 200
    ramp = np.minimum(1.0, np.minimum(np.arange(segment), segment - 1 - np.arange(segment)) / 50.0)[:, None]
    speeds = np.concatenate([ramp * truth.kinematics.inverse([0.2 * np.cos(a), 0.2 * np.sin(a), 0.3 * np.sin(3 * a)])
                             for a in np.radians(np.arange(0, 360, 60) + 10)])
    acceleration = np.gradient(speeds, dt, axis=0)
    dyn = truth.dynamics
    torque = acceleration @ dyn.mass_matrix.T + speeds @ dyn.friction_matrix.T + dyn.coulomb_torque(speeds)
    time = dt * np.arange(len(speeds))
    arrays = RecordingArrays(time, np.cumsum(speeds, axis=0) * dt, speeds, torque, [])
    fit = fit_dynamics(arrays, signed)
    params, info = fit.parameters, fit.info
    assert params.roller_friction_ratio == pytest.approx(ratio)
    assert info['roller_friction_ratio'] == pytest.approx(ratio)


def _youbot_drive(rotate, seconds=12.0, dt=0.01, noise=0.02, seed=3, model=None, speed_noise=0.0,
                  coulomb=None, pace=1.0):
    """Torques of the youBot profile's own dynamics (per-wheel Coulomb friction; ``coulomb``
    (speeds) -> torque instead, if given) on a drive in changing directions, with or without
    rotation, at ``pace`` times its speeds, plus white torque noise [N·m] and white noise on the
    speed readings [rad/s]: (model, RecordingArrays)."""
    from youbot_fdi.fdi.identify import RecordingArrays
    model = model or load_model('youbot')
    time = np.arange(0.0, seconds, dt)
    body = np.column_stack([0.4 * np.sin(2.3 * time), 0.3 * np.sin(1.7 * time + 1.0),
                            (2.0 * np.sin(2.9 * time) if rotate else 0.0 * time)])
    speeds = pace * body @ model.kinematics.jacobian.T
    acceleration = np.gradient(speeds, dt, axis=0)
    dyn = model.dynamics
    friction = dyn.coulomb_torque(speeds) if coulomb is None else coulomb(speeds)
    torque = acceleration @ dyn.mass_matrix.T + speeds @ dyn.friction_matrix.T + friction
    rng = np.random.default_rng(seed)
    torque = torque + rng.normal(0.0, noise, torque.shape)
    readings = speeds + rng.normal(0.0, speed_noise, speeds.shape) if speed_noise else speeds
    return model, RecordingArrays(time, np.cumsum(speeds, axis=0) * dt, readings, torque, [])


def _with_coulomb(level):
    """The youBot profile with per-wheel Coulomb friction ``level`` [N·m]."""
    return _with_dynamics(load_model('youbot'), coulomb_friction=(level,) * 4)


def test_a_noisy_fast_speed_reading_is_smoothed_until_its_acceleration_noise_is_a_small_share():
    """Errors in variables: noise on the acceleration (the inertias' regressor) biases the
    inertias towards zero by noise / (noise + spread). Speed readings with 0.3 rad/s of white
    noise at 500 Hz, differentiated over SAVGOL_WINDOW samples (a gain of
    1 / (dt sqrt(sum j^2)) = 64.5 /s: 19 rad/s^2 of noise against the drive's 37), lose a fifth of
    the inertia: the window grows until the noise is at most ATTENUATION_SHARE of the spread
    (the closed form at the window chosen), and the translational inertia comes back within 5 %.
    Noise-free readings keep the short window."""
    from youbot_fdi.fdi.identify import (ATTENUATION_SHARE, SAVGOL_WINDOW, _smooth, fit_dynamics,
                                         smoothing_window, speed_noise)
    from youbot_fdi.fdi.recursions import savgol_filter
    dt, sigma = 0.002, 0.3
    model, clean = _youbot_drive(rotate=True, dt=dt)
    assert smoothing_window(clean.velocity, dt, speed_noise(clean)) == SAVGOL_WINDOW
    _, noisy = _youbot_drive(rotate=True, dt=dt, speed_noise=sigma)
    assert speed_noise(noisy) == pytest.approx(sigma, rel=0.05)
    window = smoothing_window(noisy.velocity, dt, sigma)
    half = window // 2
    gain_squared = 3.0 / (dt ** 2 * half * (half + 1) * (2 * half + 1))
    spread = np.var(savgol_filter(noisy.velocity, window, 2, deriv=1, delta=dt))
    assert window > SAVGOL_WINDOW and sigma ** 2 * gain_squared <= ATTENUATION_SHARE * spread
    short = np.var(_smooth(noisy.velocity, dt, deriv=1))
    assert sigma ** 2 * 3.0 / (dt ** 2 * 4 * 5 * 9) > 0.2 * short  # the short window's: a fifth noise
    truth = model.dynamics.parameters
    found = fit_dynamics(noisy, model).parameters
    sideways = float(model.kinematics.forward_matrix[0] @ model.kinematics.forward_matrix[0])
    assert found.mass * sideways + found.wheel_inertia[0] == pytest.approx(
        truth.mass * sideways + truth.wheel_inertia[0], rel=0.05)


def test_a_wider_coulomb_step_that_fits_as_well_widens_the_stated_friction_deviation():
    """The model's Coulomb step (tanh at coulomb_velocity_scale) is a smoothing whose width it does
    not know. Torques whose Coulomb part grows over ten times the width (rolling resistance
    building up), on a drive slow enough to stay within a few such widths (a tenth of the
    usual pace), are fitted best by the wider step, and the narrow fit's viscous friction is off
    by more than its noise says: the stated deviation includes the change (``uncertainty_law``)
    and puts the truth within two of it. Torques with the model's own law rule the wider steps
    out (their squared error well above the margin), and the drag's free column takes up noise
    only: the change added is within the noise's deviation."""
    from youbot_fdi.fdi.identify import fit_dynamics
    model = _with_coulomb(0.05)
    scale = model.dynamics.parameters.coulomb_velocity_scale
    truth = model.dynamics.parameters.viscous_friction[0]

    def wide(speeds):
        return 0.05 * np.tanh(speeds / (10.0 * scale))

    _, arrays = _youbot_drive(rotate=True, model=model, noise=0.002, coulomb=wide, pace=0.1)
    fit = fit_dynamics(arrays, model)
    law, sd = fit.info['uncertainty_law'], fit.info['uncertainty']
    found = fit.parameters.viscous_friction
    for j in range(4):
        name = f'viscous_friction[{j}]'
        assert abs(found[j] - truth) > 2.0 * fit.info['uncertainty_noise'][name]  # the narrow law misses
        assert law[name] > 0.0 and sd[name] >= law[name]
        assert abs(found[j] - truth) <= 2.0 * sd[name]
    _, arrays = _youbot_drive(rotate=True, model=model, noise=0.002, pace=0.1)
    fit = fit_dynamics(arrays, model)
    assert all(fit.info['uncertainty_law'][name] <= fit.info['uncertainty_noise'][name]
               for name in fit.info['uncertainty_law'])


def test_the_rollers_drag_left_out_widens_the_stated_friction_deviation_where_it_fits_better():
    """The rollers' drag (``roller_drag_torque``: a floor holding back the gliding rollers) is
    fitted only on request. Torques with a drag of 0.1 N·m, fitted without it: the viscous term
    takes part of it (0.0405 against 0.035), by more than the noise says; the fit with the drag
    explains the torque better, and the change to it is in the stated deviation, which then
    puts the truth within two of it."""
    from youbot_fdi.fdi.identify import fit_dynamics
    model = _with_coulomb(0.05)
    truth = _with_dynamics(model, roller_drag=0.1).dynamics

    def with_drag(speeds):
        return truth.coulomb_torque(speeds) + truth.roller_drag_torque(speeds)

    _, arrays = _youbot_drive(rotate=True, model=model, noise=0.002, coulomb=with_drag)
    fit = fit_dynamics(arrays, model)
    viscous = model.dynamics.parameters.viscous_friction[0]
    for j, found in enumerate(fit.parameters.viscous_friction):
        name = f'viscous_friction[{j}]'
        assert abs(found - viscous) > 2.0 * fit.info['uncertainty_noise'][name]
        assert abs(found - viscous) <= 2.0 * fit.info['uncertainty'][name]


def test_identify_states_uncertainty_and_keeps_what_a_drive_does_not_excite_at_its_prior():
    """Wheel torques tell two inertia combinations of a base symmetric in x and y apart, the
    translational ``m |F_x|^2 + J_w`` and the rotational ``J_z |F_z|^2 + J_w`` (F the forward
    kinematics' rows), never the three parameters: the prior decides the rest.

    A drive without rotation says nothing about J_z: the fit names it not excited and leaves it
    at the prior with the prior's spread. With rotation, from a prior 30 % off: both combinations
    come back within 2 %, and each parameter lies within three of its stated standard deviations
    of the truth (the interval is honest where the data cannot separate them)."""
    from dataclasses import replace
    from youbot_fdi.fdi.identify import fit_dynamics
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.model.profile import PlatformModel
    settings = FdiSettings()
    model, arrays = _youbot_drive(rotate=False)
    truth = model.dynamics.parameters
    fit = fit_dynamics(arrays, model, settings)
    sd, prior_sd = fit.info['uncertainty'], fit.info['prior_sd']
    assert 'yaw_inertia' in fit.info['unexcited']
    assert fit.parameters.yaw_inertia == pytest.approx(truth.yaw_inertia, rel=1e-3)
    assert sd['yaw_inertia'] == pytest.approx(prior_sd['yaw_inertia'], rel=1e-3)
    assert prior_sd['yaw_inertia'] == pytest.approx(settings.prior_inertia_sd * truth.yaw_inertia)

    model, arrays = _youbot_drive(rotate=True)
    off = replace(truth, mass=1.3 * truth.mass, yaw_inertia=1.3 * truth.yaw_inertia,
                  wheel_inertia=tuple(1.3 * w for w in truth.wheel_inertia))
    fit = fit_dynamics(arrays, PlatformModel(replace(model.profile, dynamics=off)), settings)
    found, sd = fit.parameters, fit.info['uncertainty']
    rows = model.kinematics.forward_matrix
    sideways, turning = float(rows[0] @ rows[0]), float(rows[2] @ rows[2])

    def combinations(p):
        return (p.mass * sideways + p.wheel_inertia[0], p.yaw_inertia * turning + p.wheel_inertia[0])

    assert combinations(found) == pytest.approx(combinations(truth), rel=0.02)
    assert abs(found.mass - truth.mass) <= 3.0 * sd['mass']
    assert abs(found.yaw_inertia - truth.yaw_inertia) <= 3.0 * sd['yaw_inertia']
    assert abs(found.wheel_inertia[0] - truth.wheel_inertia[0]) <= 3.0 * sd['wheel_inertia']


def _youbot_loop_drive(period, seconds):
    """The youBot profile's own base under its own firmware loop (BaseSimulator, every 1 ms),
    commanded in velocity mode with a target that changes at each reading's instant, read every
    ``period`` [s] just before the next command acts: (model, RecordingArrays)."""
    from youbot_fdi.fdi.identify import RecordingArrays
    from youbot_fdi.model.firmware import ControlMode
    from youbot_fdi.model.simulation import BaseSimulator
    from youbot_fdi.samples import CommandSample
    model = load_model('youbot')
    every = int(round(period / model.firmware.period))
    reading = np.arange(0.0, seconds, period)
    body = np.column_stack([0.4 * np.sin(2.3 * reading), 0.3 * np.sin(1.7 * reading + 1.0),
                            1.5 * np.sin(2.9 * reading)])
    targets = body @ model.kinematics.jacobian.T  # one per reading, held until the next
    run = BaseSimulator(model).run(np.repeat(targets, every, axis=0), ControlMode.VELOCITY)
    pick = np.arange(every - 1, len(run['time']), every)
    signs = model.kinematics.drive_signs  # commands are in the driver's convention
    commands = [CommandSample(float(t), 'velocity', signs * v) for t, v in zip(reading, targets)]
    return model, RecordingArrays(run['time'][pick] - model.firmware.period, run['position'][pick],
                                  run['velocity'][pick], run['torque'][pick], commands)


def test_a_loop_the_readings_do_not_see_answer_moves_the_priors_inertias_and_its_gains_are_found():
    """The youBot read at 20 Hz while its loop answers each command within about 30 ms: the
    readings see under half of the answer (readings_seen_share), the inertias fitted to them come
    out low (the wheel's at its bound), so the firmware loop, stepped at its own 1 ms, would move
    a base that weighs next to nothing (unstable there: gains and delay then come out anywhere,
    k_i 64 against 8.8 and a delay of -52 ms before this). ``identify`` keeps the fitted inertias
    for the readings and gives the loop the prior's (``loop_inertias``, here the truth): the
    loop's gains are the truth's (within 5 %), its delay within the readings' interval, and
    the command path predicts the speeds within 1 % of their range."""
    from youbot_fdi.app.config import residual_data_for
    from youbot_fdi.fdi.identify import identify
    from youbot_fdi.fdi.settings import FdiSettings
    model, arrays = _youbot_loop_drive(0.05, 40.0)
    settings = FdiSettings()
    result = identify(arrays, model, settings, residual_data_for(model, settings), learn=False)
    truth, found = model.profile, result.profile
    assert result.info['readings_seen_share'] < 1.0 - settings.prior_inertia_sd
    assert found.dynamics.wheel_inertia[0] < 0.5 * truth.dynamics.wheel_inertia[0]
    assert found.dynamics.loop_inertias == (truth.dynamics.mass, truth.dynamics.yaw_inertia,
                                            truth.dynamics.wheel_inertia[0])
    assert 'prior' in result.info['loop_inertias']
    assert found.firmware.velocity_kp == pytest.approx(truth.firmware.velocity_kp, rel=0.05)
    assert found.firmware.velocity_ki == pytest.approx(truth.firmware.velocity_ki, rel=0.05)
    # the true delay is 0; the command path takes commands at the readings, so a delay shorter
    # than their 50 ms moves no command across one: any of those fits alike
    assert abs(result.fdi['input_delay']) < 0.05
    assert max(result.nrmse_commands) < 0.01


def test_the_loop_moves_its_own_inertias_and_the_readings_keep_the_fitted_ones():
    """``WheelDynamics.loop``: the dynamics themselves without ``loop_inertias``; with them, the
    report's M of those inertias, the friction kept. The observer's command path steps that loop
    (a model with loop inertias predicts from commands exactly what the model with those
    inertias does), while the torque it explains from the readings keeps the fitted inertias.
    (Without friction: the load factor, which the explained torque moves, scales the friction
    the path feels.)"""
    from dataclasses import replace
    from youbot_fdi.fdi.identify import _block
    from youbot_fdi.fdi.observer import ModelObserver
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.model.profile import PlatformModel
    model, arrays = _youbot_loop_drive(0.01, 3.0)
    assert model.dynamics.loop is model.dynamics
    other = PlatformModel(replace(model.profile, dynamics=replace(
        model.profile.dynamics, loop_inertias=(30.0, 1.2, 0.02)))).dynamics.loop
    np.testing.assert_allclose(other.mass_matrix, report_mass_matrix(30.0, 1.2, 0.02), rtol=1e-12)
    np.testing.assert_array_equal(other.friction_matrix, model.dynamics.friction_matrix)
    np.testing.assert_array_equal(other.coulomb, model.dynamics.coulomb)
    assert other.parameters.loop_inertias == ()
    zeros = (0.0,) * model.dynamics.n_wheels
    truth = replace(model.profile.dynamics, viscous_friction=zeros, coulomb_friction=zeros,
                    roller_drag=0.0)
    model = PlatformModel(replace(model.profile, dynamics=truth))
    light = replace(truth, mass=0.5 * truth.mass, yaw_inertia=0.5 * truth.yaw_inertia,
                    wheel_inertia=tuple(0.1 * w for w in truth.wheel_inertia))
    fitted = PlatformModel(replace(model.profile, dynamics=light))
    looped = PlatformModel(replace(model.profile, dynamics=replace(
        light, loop_inertias=(truth.mass, truth.yaw_inertia, truth.wheel_inertia[0]))))
    settings = FdiSettings()

    def predicted(of):
        return ModelObserver(of, settings).update_batch(*_block(of, arrays))

    own, light_only, both = predicted(model), predicted(fitted), predicted(looped)
    np.testing.assert_allclose(both.from_commands, own.from_commands, rtol=1e-9, atol=1e-9)
    assert np.abs(light_only.from_commands - own.from_commands).max() > 0.1
    np.testing.assert_allclose(both.explained, light_only.explained, rtol=1e-12, atol=1e-12)
    assert np.abs(both.explained - own.explained).max() > 1e-3


def test_correlation_inflation_is_one_for_white_noise_and_follows_an_ar1_process():
    """White residuals hold as many independent samples as rows (inflation ~1); an AR(1) with
    coefficient a holds (1 - a) / (1 + a) as many, the long-run variance ratio, up to the
    Bartlett weights' taper over the lags counted."""
    from youbot_fdi.fdi.identify import correlation_inflation
    rng = np.random.default_rng(0)
    white = rng.normal(size=(20000, 2))
    assert correlation_inflation(white, 40) == pytest.approx(1.0, abs=0.1)
    a, lags = 0.5, 200
    ar = scipy.signal.lfilter([1.0], [1.0, -a], rng.normal(size=(40000, 2)), axis=0)
    rho = a ** np.arange(1, lags + 1)
    expected = 1.0 + 2.0 * np.sum((1.0 - np.arange(1, lags + 1) / (lags + 1.0)) * rho)
    assert (1.0 + a) / (1.0 - a) == pytest.approx(3.0)
    assert correlation_inflation(ar, lags) == pytest.approx(expected, rel=0.1)


def test_stated_deviation_grows_where_the_recording_disagrees_with_itself():
    """The same drive, once as the model says and once with the viscous friction doubled halfway
    (a model that misses: no single D explains it). Consistent: the block jackknife (the fit's
    spread with each tenth of the recording left out) adds little to the noise's 10^-4. Changed:
    the residual's autocorrelation inflates the noise, the jackknife more (about 2x), and the
    stated deviation, a hundred times the consistent one, puts every wheel's D within two of
    it from the halves' mean 0.0525."""
    from dataclasses import replace
    from youbot_fdi.fdi.identify import fit_dynamics
    model, arrays = _youbot_drive(rotate=True)
    fit = fit_dynamics(arrays, model)
    consistent = fit.info['uncertainty']['viscous_friction[0]']
    assert consistent < 3.0 * fit.info['uncertainty_noise']['viscous_friction[0]']
    torque = arrays.torque.copy()
    half = len(torque) // 2
    torque[half:] += arrays.velocity[half:] * 0.035  # D doubles halfway [N·m·s/rad]
    changed = fit_dynamics(replace(arrays, torque=torque), model)
    for j, value in enumerate(changed.parameters.viscous_friction):
        stated = changed.info['uncertainty'][f'viscous_friction[{j}]']
        assert stated >= changed.info['uncertainty_noise'][f'viscous_friction[{j}]']
        assert stated > 50.0 * consistent
        assert abs(value - 0.0525) <= 2.0 * stated


def test_roller_drag_torque_matches_the_hand_derived_contact_geometry():
    """A mecanum wheel (roller angle gamma = +-45 deg) driven sideways at v_y: n . v_c = r
    theta_dot sin(gamma) gives theta_dot = -v/r (gamma = 45 deg, the front left) or +v/r (-45 deg,
    the front right), and the rim's motion left for the rollers, v_c - r theta_dot h, is (v, v) or
    (-v, v): a slide u = +sqrt(2) v or -sqrt(2) v along s = (cos gamma, sin gamma). The floor holds
    the roller back along s, and its part along the rolling direction turns the wheel: the torque
    the motor feels is -D_r cos(gamma) tanh(u / (r v_s)). Driving straight ahead the rollers do not
    turn (u = 0): no drag. Omni wheels (gamma = 90 deg) never feel it."""
    from dataclasses import replace
    from youbot_fdi.model.dynamics import WheelDynamics
    model = load_model('youbot')
    drag = 0.08  # [N·m]
    dynamics = WheelDynamics(model.kinematics, replace(model.dynamics.parameters, roller_drag=drag))
    scale = dynamics.parameters.coulomb_velocity_scale
    for v in (0.0005, 0.01, 0.3):  # [m/s]: within the tanh's width and far beyond it
        speeds = model.kinematics.inverse(np.array([0.0, v, 0.0]))
        torque = dynamics.roller_drag_torque(speeds)
        for j, wheel in enumerate(model.kinematics.platform.wheels):
            slide = math.copysign(math.sqrt(2.0) * v, wheel.roller_angle) / wheel.radius
            expected = -drag * math.cos(wheel.roller_angle) * math.tanh(slide / scale)
            assert torque[j] == pytest.approx(expected, rel=1e-9, abs=1e-15)
    ahead = model.kinematics.inverse(np.array([0.4, 0.0, 0.0]))
    assert np.allclose(dynamics.roller_drag_torque(ahead), 0.0, atol=1e-12)
    # the torque the motors feel includes it
    sideways = model.kinematics.inverse(np.array([0.0, 0.3, 0.0]))
    assert np.allclose(dynamics.coulomb_torque(sideways) - model.dynamics.coulomb_torque(sideways),
                       dynamics.roller_drag_torque(sideways))
    omni = load_model('robotino')
    omni_dynamics = WheelDynamics(omni.kinematics, replace(omni.dynamics.parameters, roller_drag=drag))
    assert not omni_dynamics.has_drag
    assert np.all(omni_dynamics.roller_drag_torque(omni.kinematics.inverse(np.array([0.0, 0.3, 0.0]))) == 0.0)


def test_identify_finds_the_rollers_drag_and_the_viscous_friction_it_would_bias():
    """Torques with a roller drag (one D_r for the base) on a drive in changing directions: the
    fit asked to (``fit_roller_drag``) finds D_r and the per-wheel viscous friction within their stated intervals (three
    standard deviations); without the drag column the viscous friction would absorb it (the
    drag grows with the slide, and the slide with the speeds)."""
    from dataclasses import replace
    from youbot_fdi.fdi.identify import RecordingArrays, fit_dynamics
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.model.dynamics import WheelDynamics
    model = load_model('youbot')
    truth = replace(model.dynamics.parameters, roller_drag=0.06)
    dynamics = WheelDynamics(model.kinematics, truth)
    dt = 0.01
    time = np.arange(0.0, 30.0, dt)
    body = np.column_stack([0.3 * np.sin(0.9 * time), 0.3 * np.sin(0.7 * time + 1.0),
                            1.0 * np.sin(1.3 * time)])
    speeds = body @ model.kinematics.jacobian.T
    acceleration = np.gradient(speeds, dt, axis=0)
    torque = (acceleration @ dynamics.mass_matrix.T + speeds @ dynamics.friction_matrix.T
              + dynamics.coulomb_torque(speeds))
    torque = torque + np.random.default_rng(5).normal(0.0, 0.01, torque.shape)
    arrays = RecordingArrays(time, np.cumsum(speeds, axis=0) * dt, speeds, torque, [])
    fit = fit_dynamics(arrays, model, FdiSettings(fit_roller_drag=True))
    found, sd = fit.parameters, fit.info['uncertainty']
    assert 'roller_drag' not in fit.info['unexcited']
    assert abs(found.roller_drag - truth.roller_drag) <= 3.0 * sd['roller_drag']
    assert found.roller_drag == pytest.approx(truth.roller_drag, rel=0.1)
    for j in range(model.dynamics.n_wheels):
        assert abs(found.viscous_friction[j] - truth.viscous_friction[j]) <= 3.0 * sd[f'viscous_friction[{j}]']
    # not fitted (the default): held at the prior's value; a prior without it leaves the
    # viscous friction to absorb it, a prior with the true drag takes it as known torque
    held = fit_dynamics(arrays, model, FdiSettings()).parameters
    assert held.roller_drag == model.dynamics.parameters.roller_drag == 0.0
    assert max(abs(v - t) for v, t in zip(held.viscous_friction, truth.viscous_friction)) > \
        max(abs(v - t) for v, t in zip(found.viscous_friction, truth.viscous_friction))
    from youbot_fdi.model.profile import PlatformModel
    informed = fit_dynamics(arrays, PlatformModel(replace(model.profile, dynamics=truth)), FdiSettings())
    assert informed.parameters.roller_drag == truth.roller_drag
    for j in range(model.dynamics.n_wheels):
        assert abs(informed.parameters.viscous_friction[j] - truth.viscous_friction[j]) <= \
            3.0 * informed.info['uncertainty'][f'viscous_friction[{j}]']


def test_inertias_readings_taken_late_in_the_loops_answer_cannot_tell_span_the_prior():
    """Readings at 16 Hz of a youBot whose velocity loop settles within 37 ms (the prior's, whose
    inertias are 30 % above the truth: response_time_constant): commands sent at each reading's
    instant reach the wheels just after it, the readings see 38 % of the loop's answer
    (readings_seen_share), less than 1 - prior_inertia_sd: the stated deviations of mass and
    inertias reach the prior's values, the values stay the fit's, and the fit says why. The same
    drive with the commands half an interval later (89 % seen) states what the fit alone states."""
    from dataclasses import replace
    from youbot_fdi.fdi.identify import fit_dynamics, readings_seen_share
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.model.firmware import response_time_constant
    from youbot_fdi.model.profile import PlatformModel
    from youbot_fdi.samples import CommandSample
    settings, period = FdiSettings(), 0.0625
    model, arrays = _youbot_drive(rotate=True, seconds=60.0, dt=period)
    truth = model.dynamics.parameters
    off = replace(truth, mass=1.3 * truth.mass, yaw_inertia=1.3 * truth.yaw_inertia,
                   wheel_inertia=tuple(1.3 * w for w in truth.wheel_inertia))
    prior = PlatformModel(replace(model.profile, dynamics=off))
    tau = response_time_constant(prior.dynamics, prior.drive.torque_per_amp, prior.firmware)
    assert 0.035 < tau < 0.04

    def sent(delay):
        return replace(arrays, commands=[CommandSample(float(t + delay), 'velocity', v)
                                          for t, v in zip(arrays.time, arrays.velocity)])

    plain = fit_dynamics(arrays, prior, settings)
    assert plain.info['readings_seen_share'] is None and 'inertias_unseen' not in plain.info
    late = fit_dynamics(sent(0.0), prior, settings)
    share = readings_seen_share(arrays.time, sent(0.0).command_batch, tau)
    assert late.info['readings_seen_share'] == pytest.approx(share, abs=1e-3)
    assert share < 1.0 - settings.prior_inertia_sd
    assert 'between them' in late.info['inertias_unseen']
    assert late.parameters == plain.parameters
    found = late.parameters
    for name, value, before in (('mass', found.mass, off.mass),
                                ('yaw_inertia', found.yaw_inertia, off.yaw_inertia),
                                ('wheel_inertia', found.wheel_inertia[0], off.wheel_inertia[0])):
        assert late.info['uncertainty'][name] >= abs(value - before) > 0.0
    assert late.info['uncertainty']['viscous_friction[0]'] == plain.info['uncertainty']['viscous_friction[0]']
    halfway = fit_dynamics(sent(period / 2), prior, settings)
    assert halfway.info['readings_seen_share'] > 0.8 and 'inertias_unseen' not in halfway.info
    assert halfway.info['uncertainty'] == plain.info['uncertainty']
