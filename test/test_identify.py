"""Identification's search helpers, against hand-derived answers."""
import numpy as np
import pytest
import scipy.optimize

from youbot_fdi.fdi.identify import (BroydenJacobian, DELAY_COARSE_STEPS, descend_grid, for_search,
                                     RecordingArrays, search_grid, SEARCH_SECONDS, SEARCH_WINDOWS)

FAST_EXCEPT = ('test_the_pi_gains_are_fitted_with_the_rollers_drag_the_fdis_model_leaves_out',)


def test_the_delay_grid_is_searched_coarsely_then_step_by_step_around_the_best():
    """Errors (d - 7)^2 on a grid 0..19, DELAY_COARSE_STEPS = 4: the coarse points 0, 4, 8, 12,
    16 and the last, 19; the best of them is 8, and every point within 4 steps of it (5..11)
    is tried: 7 wins. Nothing else is tried."""
    assert DELAY_COARSE_STEPS == 4
    grid = np.arange(20.0)
    tried = []

    def error(d):
        tried.append(d)
        return (d - 7.0) ** 2

    best, errors = search_grid(error, grid)
    assert best == 7
    assert sorted(tried) == [0.0, 4.0, 5.0, 6.0, 7.0, 8.0, 9.0, 10.0, 11.0, 12.0, 16.0, 19.0]
    assert np.isfinite(errors).sum() == len(tried) and errors[7] == 0.0


def test_the_delay_walks_downhill_a_stride_at_a_time_and_stops_at_the_minimum():
    """Errors (d - 7)^2 on a grid 0..19: from 3 a walk of stride 1 goes up the grid to 7 and
    tries 8 (worse); the other way from 3, 2 is worse: nothing else is tried. With stride 4
    from 18: 14, 10, 6 (better each time), 2 (worse); the other way 22 is off the grid: 6."""
    grid = np.arange(20.0)
    tried = []

    def error(d):
        tried.append(d)
        return (d - 7.0) ** 2

    errors = np.full(len(grid), np.nan)
    assert descend_grid(error, grid, 3, errors) == 7
    assert sorted(tried) == [2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    assert np.isnan(errors[9:]).all() and np.isnan(errors[:2]).all()
    tried.clear()
    assert descend_grid(error, grid, 18, np.full(len(grid), np.nan), stride=4) == 6
    assert tried == [18.0, 14.0, 10.0, 6.0, 2.0]


def test_a_walk_that_wins_a_tie_one_way_still_looks_the_other_way():
    """A plateau at 1.0 over 5..9 (its point 6 a hair lower) and a valley at 2-3: from 5 the walk
    up takes 6 (lower by 1e-12) and stops at 7; the walk down starts from 5 again, not from 6,
    and finds the valley at 3 (0.5) through 4 (0.8), stopping at 2 (0.6)."""
    grid = np.arange(10.0)
    values = np.array([2.0, 1.5, 0.6, 0.5, 0.8, 1.0, 1.0 - 1e-12, 1.0, 1.0, 1.0])
    assert descend_grid(lambda d: values[int(d)], grid, 5, np.full(len(grid), np.nan)) == 3


def test_the_searches_see_at_most_search_seconds_in_windows_over_the_whole_recording():
    """A 300 s recording at 100 Hz: the searches get SEARCH_SECONDS of it, in SEARCH_WINDOWS
    windows, the first at its start and the last ending at its end; a short one is kept whole."""
    time = np.arange(0.0, 300.0, 0.01)
    ones = np.ones((len(time), 4))
    arrays = RecordingArrays(time, ones, ones, ones, [])
    searched = for_search(arrays)
    assert len(searched.time) == pytest.approx(SEARCH_SECONDS / 0.01, rel=0.01)
    jumps = np.flatnonzero(np.diff(searched.time) > 0.02)
    assert len(jumps) == SEARCH_WINDOWS - 1
    assert searched.time[0] == 0.0 and searched.time[-1] == pytest.approx(time[-1], abs=0.011)
    short = RecordingArrays(time[:2000], ones[:2000], ones[:2000], ones[:2000], [])
    assert len(for_search(short).time) == 2000


def test_wheels_that_never_turn_keep_their_friction_prior_and_are_named():
    """Only wheel 0 turns (torque = 0.04 N·m·s/rad x its speed, exact): its viscous friction comes
    back as 0.04; the other wheels' columns are zero, so their friction is the prior's (0.035),
    named not excited, with the prior's deviation (the prior times prior_friction_sd)."""
    from youbot_fdi.fdi.identify import fit_dynamics
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.model import load_model
    model, settings = load_model('youbot'), FdiSettings()
    time = np.arange(0.0, 5.0, 0.01)
    speed = np.zeros((len(time), 4))
    speed[:, 0] = np.sin(time)
    fit = fit_dynamics(RecordingArrays(time, speed, speed, 0.04 * speed, []), model, settings)
    assert fit.parameters.viscous_friction[0] == pytest.approx(0.04, rel=1e-6)
    prior = model.dynamics.parameters.viscous_friction
    for j in (1, 2, 3):
        assert fit.parameters.viscous_friction[j] == pytest.approx(prior[j], rel=1e-6)
        assert f'viscous_friction[{j}]' in fit.info['unexcited']
        assert fit.info['uncertainty'][f'viscous_friction[{j}]'] == pytest.approx(
            settings.prior_friction_sd * prior[j], rel=1e-3)
    assert 'viscous_friction[0]' not in fit.info['unexcited']


def test_our_savitzky_golay_filter_is_scipys():
    """identify smooths with its own Savitzky-Golay filter (scipy.signal's import takes longer
    than the filtering): the same values as scipy.signal.savgol_filter, edges included."""
    import scipy.signal

    from youbot_fdi.fdi.recursions import savgol_filter
    rng = np.random.default_rng(3)
    for shape in ((40,), (120, 4), (9, 3)):
        values = rng.normal(size=shape).cumsum(axis=0)
        for window in (5, 9):
            for deriv in (0, 1, 2):
                ours = savgol_filter(values, window, 2, deriv, delta=0.01)
                theirs = scipy.signal.savgol_filter(values, window, 2, deriv=deriv, delta=0.01, axis=0)
                np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-9 * np.abs(theirs).max())
    with pytest.raises(ValueError, match='window must be odd'):
        savgol_filter(np.zeros(10), 4, 2)


def test_a_driver_that_holds_its_last_command_is_told_from_one_with_a_watchdog():
    """One command, 2 rad/s on every wheel, sent once at t = 0 (a host that sends on change) in
    a 3 s recording at 100 Hz: every sample after the watchdog's 0.25 s is past it. A driver
    that holds the command keeps the wheels at 2 rad/s there, one with a watchdog stops them:
    ``commands_held`` says which the speeds show. A command with every sample leaves no sample
    past the watchdog, and nothing to tell (False)."""
    from youbot_fdi.fdi.identify import commands_held, commands_past_watchdog
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.model import load_model
    from youbot_fdi.samples import CommandSample
    model, settings = load_model('youbot'), FdiSettings()
    assert settings.command_timeout == 0.25
    time = np.round(np.arange(0.0, 3.0, 0.01), 6)
    signs = model.kinematics.drive_signs  # commands are in the driver's convention
    once = [CommandSample(0.0, 'velocity', signs * 2.0)]
    viscous = np.asarray(model.dynamics.parameters.viscous_friction)

    def recording(speed, commands):
        speed = np.repeat(speed[:, None], 4, axis=1)
        return RecordingArrays(time, np.cumsum(speed, axis=0) * 0.01, speed, viscous * speed, commands)

    held = recording(np.full(len(time), 2.0), once)
    assert commands_past_watchdog(held, settings).tolist() == (time > 0.25 + 1e-9).tolist()
    assert commands_held(model, held, settings)
    stopped = recording(np.where(time <= 0.25, 2.0, 0.0), once)
    assert not commands_held(model, stopped, settings)
    every_sample = [CommandSample(float(t), 'velocity', signs * 2.0) for t in time]
    dense = recording(np.full(len(time), 2.0), every_sample)
    assert not commands_past_watchdog(dense, settings).any()
    assert not commands_held(model, dense, settings)


def test_the_share_of_the_loops_answer_the_readings_see_follows_where_they_fall_in_it():
    """Readings every T = 50 ms, a loop whose answer to a command fades within tau = 30 ms.
    Commands changing at each reading's instant reach the wheels just after it: every reading is
    T after the last change, and sees exp(-T / tau) of the answer, whose mean over time is
    (tau / T)(1 - exp(-T / tau)); commands half an interval after each reading: exp(-T / 2 tau)
    over the same mean (to the recording's last half interval). Commands repeating the value
    they had are no change. Commands at random instants: the readings fall at every phase and
    see the mean (share 1, to the sampling's noise). No velocity commands: nothing to judge."""
    from youbot_fdi.fdi.identify import readings_seen_share
    from youbot_fdi.samples import CommandBatch
    period, tau = 0.05, 0.03
    time = np.arange(0.0, 60.0, period)
    mean = tau / period * -np.expm1(-period / tau)

    def commands(stamps, values=None):
        values = np.arange(len(stamps), dtype=float) if values is None else values
        return CommandBatch(np.asarray(stamps), np.ones(len(stamps), dtype=bool),
                            np.repeat(values[:, None], 4, axis=1))

    aligned = readings_seen_share(time, commands(time), tau)
    assert aligned == pytest.approx(np.exp(-period / tau) / mean, rel=1e-9)
    assert aligned < 0.5
    halfway = readings_seen_share(time, commands(time + period / 2), tau)
    assert halfway == pytest.approx(np.exp(-period / (2 * tau)) / mean, rel=1e-3)
    # the same changes, each command sent twice (again at the next reading's instant)
    twice = np.repeat(np.arange(0, len(time), 2, dtype=float), 2)[:len(time)]
    assert readings_seen_share(time, commands(time, twice), tau) == pytest.approx(
        readings_seen_share(time, commands(time[::2]), tau), rel=1e-9)
    rng = np.random.default_rng(1)
    assert readings_seen_share(time, commands(np.sort(rng.uniform(0.0, 60.0, 800))), tau) == \
        pytest.approx(1.0, abs=0.1)
    effort = CommandBatch(time, np.zeros(len(time), dtype=bool), np.zeros((len(time), 4)))
    assert np.isnan(readings_seen_share(time, effort, tau))


def test_the_gain_fits_jacobian_meets_the_secant_of_each_step_and_is_exact_on_a_linear_map():
    """Residuals r(x) = M x - y, linear: the forward differences give M itself (two extra
    evaluations, none after: a Broyden update of an exact Jacobian is zero), and least squares
    with it lands on the closed form (M'M)^-1 M'y. On a nonlinear map the updated Jacobian
    meets the secant condition J1 (x1 - x0) = r(x1) - r(x0) exactly."""
    rng = np.random.default_rng(3)
    matrix, target = rng.normal(size=(50, 2)), rng.normal(size=50)
    calls = []

    def linear(x):
        calls.append(x.copy())
        return matrix @ x - target

    jacobian = BroydenJacobian(linear, 0.02)
    result = scipy.optimize.least_squares(jacobian.residuals, np.zeros(2), jac=jacobian, method='trf',
                                          xtol=1e-12, ftol=1e-12)
    assert np.allclose(jacobian.matrix, matrix, atol=1e-9)
    assert np.allclose(result.x, np.linalg.solve(matrix.T @ matrix, matrix.T @ target), atol=1e-8)
    assert len(calls) == result.nfev + 2  # the differences once, every update free

    def curved(x):
        return np.array([np.exp(x[0]) - x[1], x[0] * x[1], np.sin(x[1])])

    secant = BroydenJacobian(curved, 0.02)
    x0, x1 = np.array([0.1, 0.2]), np.array([0.3, -0.1])
    secant.residuals(x0)
    secant(x0)
    secant.residuals(x1)
    updated = secant(x1)
    assert np.allclose(updated @ (x1 - x0), curved(x1) - curved(x0), atol=1e-12)


def test_identify_names_the_wheels_whose_friction_split_it_could_not_tell():
    """A wheel whose Coulomb (0.05 N·m) or viscous (0.03 N·m·s/rad) friction lies within two
    standard deviations of 0 is named: 0.05 <= 2 x 0.03, 0.03 <= 2 x 0.02; one known to 0.02 and
    0.01 is not, nor one without a stated deviation."""
    from types import SimpleNamespace
    from youbot_fdi.cli.identify import _split_unknown
    dynamics = SimpleNamespace(coulomb_friction=(0.05,) * 4, viscous_friction=(0.03,) * 4)
    deviation = {'coulomb_friction[0]': 0.02, 'viscous_friction[0]': 0.01,
                 'coulomb_friction[1]': 0.03, 'viscous_friction[1]': 0.01,
                 'coulomb_friction[2]': 0.02, 'viscous_friction[2]': 0.02}
    assert _split_unknown(['fl', 'fr', 'bl', 'br'], dynamics, deviation) == ['fr', 'bl']


def test_the_pi_gains_are_fitted_with_the_rollers_drag_the_fdis_model_leaves_out(tmp_path):
    """A base the FDI's model did not write (bench/plant.py: its own integrator, contact and
    firmware), whose floor holds its gliding rollers back, driven 20 s in velocity mode at
    125 Hz. Its loop's k_p 1.6 A/(rad/s) and k_i 4.5 A/rad are found within 10 % by ``identify``,
    which fits them with the rollers' drag (``model_for_loop_fit``) while the FDI's model keeps
    none; fitted on the model without the drag, on this drive, the loop comes out over 1.5 times
    faster in k_p and k_i alike, the later delay taking what a rejected drag looks like."""
    from dataclasses import replace
    from youbot_fdi.app.config import residual_data_for
    from youbot_fdi.app.recordings import read_arrays
    from youbot_fdi.bench import plant, randomized
    from youbot_fdi.fdi.identify import delay_grid, fit_delay_and_gains, identify
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.model.profile import load_model, PlatformModel
    values = dict(mass=24.6, yaw_inertia=1.12, wheel_inertia=0.011, viscous=[0.07] * 4,
                  coulomb=[0.04] * 4, asymmetry=[0.0] * 4, traction=0.76, roller_resistance=0.028,
                  rolling_resistance=0.00024, torque_scale=1.0, kp=1.6, ki=4.5, current_limit=2.9,
                  current_lag=0.0017, delay=0.0005, current_mode=False, sample_rate=125.0,
                  jitter=0.0, drop=0.0, command_rate=0.0, on_change=False, quantised=False,
                  speed_reading=0, speed_lag=0.0, speed_noise=0.0, current_noise=0.01)
    params = plant.PlantParameters(**{name: np.array([v]) for name, v in values.items()})
    seconds = 20.0
    knots, twists = randomized.random_knots(np.random.default_rng(2), seconds, 0.25, 0.6, 0.5, 1.0,
                                            stop_share=0.15)
    recording = plant.simulate(params, [plant.Drive(knots, twists, seconds)], seed=2)[0]
    path = str(tmp_path / 'calibration')
    prior = load_model(randomized.PROFILE)
    randomized.write(recording, path, prior.wheel_names)
    arrays = read_arrays(path, prior)
    settings = FdiSettings()
    result = identify(arrays, prior, settings, residual_data_for(prior, settings), learn=False)
    found = result.profile.firmware
    assert result.profile.dynamics.roller_drag == 0.0  # the FDI's model: none
    assert result.info['loop_fit_roller_drag'] > 0.0
    assert found.velocity_kp == pytest.approx(values['kp'], rel=0.1)
    assert found.velocity_ki == pytest.approx(values['ki'], rel=0.1)
    without = PlatformModel(replace(prior.profile, dynamics=result.profile.dynamics))
    _, plain, _ = fit_delay_and_gains(without, for_search(arrays), delay_grid(1.0 / values['sample_rate']))
    assert plain.velocity_kp > 1.5 * values['kp'] and plain.velocity_ki > 1.5 * values['ki']
