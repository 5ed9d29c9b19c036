"""Firmware emulation: current mode, sampled and continuous velocity loops, loop stability."""
import numpy as np
import pytest

from youbot_fdi.errors import ModelError
from youbot_fdi.model import BaseSimulator, ControlMode, load_model, sampled_loop_spectral_radius

pytestmark = pytest.mark.fast  # `make check`: the unit tests of the core, under a minute


def test_report_gains_make_a_sampled_1khz_loop_unstable_on_seed_values():
    seed = load_model('seed')
    assert sampled_loop_spectral_radius(seed.dynamics, seed.drive.torque_per_amp, seed.firmware) > 1
    youbot = load_model('youbot')
    assert sampled_loop_spectral_radius(youbot.dynamics, youbot.drive.torque_per_amp,
                                        youbot.firmware) < 1


@pytest.mark.parametrize('profile', ['seed', 'youbot'])
def test_velocity_mode_tracks_a_step(profile):
    model = load_model(profile)
    simulator = BaseSimulator(model)
    target = model.kinematics.inverse((0.2, 0.1, 0.3))
    steps = int(2.0 / simulator.step_size)
    result = simulator.run(np.tile(target, (steps, 1)), ControlMode.VELOCITY)
    assert np.all(np.isfinite(result['velocity']))
    np.testing.assert_allclose(result['velocity'][-1], target, rtol=1e-3)
    # Under a loop the wheels are reached quickly: within 0.5 s to 2 %.
    np.testing.assert_allclose(result['velocity'][int(0.5 / simulator.step_size)], target,
                               rtol=0.02)


def test_sampled_loop_respects_the_current_limit():
    model = load_model('youbot')
    simulator = BaseSimulator(model)
    big_step = np.full(4, 15.0)
    result = simulator.run(np.tile(big_step, (200, 1)), ControlMode.VELOCITY)
    assert np.max(np.abs(result['current'])) <= model.drive.max_current + 1e-12
    assert np.max(np.abs(result['current'])) == pytest.approx(model.drive.max_current)


def test_current_mode_is_open_loop_torque():
    model = load_model('youbot')
    simulator = BaseSimulator(model)
    current = np.array([0.5, 0.5, 0.5, 0.5])  # kinematic convention: the base drives forward
    result = simulator.run(np.tile(current, (8000, 1)), ControlMode.CURRENT)
    torque = current * model.drive.torque_per_amp
    np.testing.assert_allclose(result['torque'][-1], torque)
    np.testing.assert_allclose(result['velocity'][-1], torque / 0.035, rtol=1e-3)
    twist = model.kinematics.forward(result['velocity'][-1])
    assert twist[0] > 0 and abs(twist[1]) < 1e-9 and abs(twist[2]) < 1e-9


def test_torque_gain_and_external_torque_change_the_response():
    model = load_model('youbot')
    nominal, weak = BaseSimulator(model), BaseSimulator(model)
    current = np.full(4, 0.5)
    for _ in range(500):
        a = nominal.step(current, ControlMode.CURRENT)
        b = weak.step(current, ControlMode.CURRENT, torque_gain=[0.2, 1, 1, 1])
    assert b.velocity[0] < a.velocity[0]
    np.testing.assert_allclose(b.torque[0], 0.2 * a.torque[0])


def test_stop_mode_brings_the_wheels_to_rest():
    model = load_model('youbot')
    simulator = BaseSimulator(model)
    simulator.reset(velocity=[5.0, -5.0, 5.0, -5.0])
    result = simulator.run(np.zeros((3000, 4)), ControlMode.MOTOR_STOP)
    np.testing.assert_allclose(result['velocity'][-1], 0.0, atol=1e-3)


def test_bad_setpoints_and_mode_mixes_are_refused():
    simulator = BaseSimulator(load_model('youbot'))
    with pytest.raises(ValueError, match='finite'):
        simulator.step([0.0, np.nan, 0.0, 0.0], ControlMode.VELOCITY)
    with pytest.raises(ModelError, match='period'):
        BaseSimulator(load_model('youbot'), step=0.01)
    seed = BaseSimulator(load_model('seed'))
    with pytest.raises(ModelError, match='mix'):
        seed.step(np.zeros(4), [ControlMode.CURRENT, ControlMode.VELOCITY] * 2)


@pytest.mark.parametrize('ki', [8.8, 2.0, 0.05, 0.0])
def test_the_loops_time_constants_match_its_characteristic_roots(ki):
    """With equal viscous friction b on every wheel the loop decouples along the mass matrix's
    eigenvectors: each mode of inertia m answers m s^2 + (b + k_t k_p) s + k_t k_i = 0 (without an
    integral gain: m s + b + k_t k_p = 0). The slowest time constant is 1 / the smallest decay rate
    of those roots, by hand."""
    from dataclasses import replace

    from youbot_fdi.model import response_time_constant, slowest_time_constant
    from youbot_fdi.model.profile import PlatformModel
    youbot = load_model('youbot')
    b = 0.05
    profile = replace(youbot.profile,
                      dynamics=replace(youbot.dynamics.parameters, viscous_friction=(b,) * 4),
                      firmware=replace(youbot.firmware, velocity_ki=ki))
    model = PlatformModel(profile)
    kt, kp = model.drive.torque_per_amp, model.firmware.velocity_kp
    rates = []
    for m in np.linalg.eigvalsh(model.dynamics.mass_matrix):
        if ki == 0.0:
            rates.append((b + kt * kp) / m)
            continue
        roots = np.roots([m, b + kt * kp, kt * ki])
        rates.append(np.min(-roots.real))
    expected = 1.0 / min(rates)
    got = slowest_time_constant(model.dynamics, model.drive.torque_per_amp, model.firmware)
    assert got == pytest.approx(expected, rel=1e-9)
    assert got > 0.5 if 0.0 < ki < 1.0 else got < 0.5  # a weak integral forgets slowly
    # the answer to a step of the target fades with the proportional modes, whatever the integral
    heaviest = float(np.max(np.linalg.eigvalsh(model.dynamics.mass_matrix)))
    answer = response_time_constant(model.dynamics, model.drive.torque_per_amp, model.firmware)
    assert answer == pytest.approx(heaviest / (b + kt * kp), rel=1e-9)
