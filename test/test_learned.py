"""Learned corrections of the physics (issue 12): the fit, its guard, the numpy evaluation shared
by the live path and replay, and identify's --physics-only."""
import numpy as np
import pytest

from youbot_fdi.errors import ConfigError
from youbot_fdi.fdi.learned import (FEATURES, fit_torque_correction, masked_wheels, TorqueCorrection,
                                    wheel_mask)

SCALE = 0.05  # [rad/s]


def synthetic(rng, truth, rows=3000, noise=0.005):
    """Speeds, accelerations and residuals (rows, wheels) from true weights (wheels, FEATURES)."""
    speed = rng.uniform(-6.0, 6.0, (rows, truth.shape[0]))
    acceleration = rng.normal(scale=20.0, size=speed.shape)
    unbounded = TorqueCorrection(truth, np.full(len(truth), np.inf), SCALE, np.full(len(truth), np.inf))
    residual = unbounded(speed, acceleration) + rng.normal(scale=noise, size=speed.shape)
    return speed, acceleration, residual


def test_the_fit_recovers_friction_that_differs_by_direction_and_a_missed_inertia():
    """Each wheel keeps what its residual has: friction by direction, an inertia share, both."""
    rng = np.random.default_rng(0)
    truth = np.array([[0.05, 0.03, 0.002, 0.0], [0.04, -0.02, 0.0, 0.001],
                      [0.0, 0.0, 0.0, -0.002], [0.05, 0.0, 0.001, 0.0]])
    speed, acceleration, residual = synthetic(rng, truth)
    correction, notes = fit_torque_correction(speed, acceleration, residual, SCALE, torque_floor=0.01)
    assert notes == []
    np.testing.assert_allclose(correction.weights, truth, atol=3e-3)
    assert np.all(correction.weights[2, :3] == 0.0)  # inertia only: its friction part not kept
    assert correction.weights[0, 3] == 0.0 and correction.weights[3, 3] == 0.0
    left = residual - correction(speed, acceleration)
    assert np.sqrt(np.mean(left ** 2)) < 0.3 * np.sqrt(np.mean(residual ** 2))
    # Bounded by what calibration saw: far outside it, the correction does not grow.
    np.testing.assert_array_less(np.abs(correction.friction(np.full(4, 100.0))), correction.limit + 1e-12)
    np.testing.assert_array_less(np.abs(correction.inertial(np.full(4, 1e4))),
                                 correction.inertia_limit + 1e-12)


def test_one_row_at_a_time_equals_a_block():
    """The live observer's batch of one gives the block's bits: the parts, the current gate of
    the inertial feature and the wheels outside the calibrated range (NaN readings included)."""
    from youbot_fdi.fdi.learned import inertial_feature
    rng = np.random.default_rng(1)
    ranges = np.tile([-2.0, 2.0], (4, 1))
    weights = rng.normal(size=(4, FEATURES))
    weights[1, :3] = 0.0  # inertia only: its speed is not checked
    correction = TorqueCorrection(weights, np.full(4, 0.5), SCALE, np.full(4, 0.5), ranges,
                                  3.0 * ranges, 0.1)
    speed, acceleration, torque, before = rng.normal(scale=2.0, size=(4, 200, 4))
    speed[5, 2] = torque[7, 0] = acceleration[9, 3] = np.nan
    friction, inertial, seen = correction.applied(speed, inertial_feature(acceleration, torque, before, 2.5))
    mask = wheel_mask(seen)
    assert 0 < np.count_nonzero(mask) < len(mask) and np.any(inertial == 0.0) and np.any(inertial != 0.0)
    for k in range(len(speed)):
        row = slice(k, k + 1)
        one = correction.applied(speed[row], inertial_feature(acceleration[row], torque[row],
                                                              before[row], 2.5))
        np.testing.assert_array_equal(one[0], friction[row])
        np.testing.assert_array_equal(one[1], inertial[row])
        assert wheel_mask(one[2])[0] == mask[k]
    unbounded = TorqueCorrection(weights, np.full(4, 0.5), SCALE, np.full(4, 0.5))
    np.testing.assert_allclose(np.array([unbounded(v, a) for v, a in zip(speed[:50], acceleration[:50])]),
                               unbounded(speed[:50], acceleration[:50]))


def test_a_wheel_that_departs_alone_is_not_learned():
    """A persistent single-wheel departure in the 'nominal' recording (a fault) is refused."""
    rng = np.random.default_rng(2)
    truth = np.array([[0.01, 0.0, 0.0, 0.0], [0.01, 0.0, 0.0, 0.0], [0.2, 0.0, 0.01, 0.0], [0.01, 0.0, 0.0, 0.0]])
    speed, acceleration, residual = synthetic(rng, truth)
    correction, notes = fit_torque_correction(speed, acceleration, residual, SCALE, torque_floor=0.02)
    assert len(notes) == 1 and 'wheel 2' in notes[0] and 'fault' in notes[0]
    assert np.all(correction.weights[2] == 0.0) and correction.limit[2] == 0.0
    assert np.any(correction.weights[0] != 0.0)


def test_too_little_motion_learns_nothing():
    still = np.zeros((500, 4))
    correction, notes = fit_torque_correction(still, still, still, SCALE, 0.01)
    assert correction is None and 'not learned' in notes[0]


def test_noise_alone_learns_nothing():
    rng = np.random.default_rng(4)
    speed = rng.uniform(-6.0, 6.0, (3000, 4))
    acceleration = rng.normal(scale=20.0, size=speed.shape)
    correction, notes = fit_torque_correction(speed, acceleration, rng.normal(scale=0.02, size=speed.shape),
                                              SCALE, 0.01)
    assert correction is None and 'physics only' in notes[-1]


def test_a_friction_only_file_reads_with_no_inertial_part():
    """A parameter file written before the inertial part (weights n x 3, no inertia_limit)."""
    old = {'weights': [[0.01, 0.0, 0.001]] * 4, 'limit': [0.1] * 4, 'speed_scale': 0.1}
    correction = TorqueCorrection.from_mapping(old, 4)
    np.testing.assert_array_equal(correction.inertial(np.full(4, 50.0)), np.zeros(4))
    again = TorqueCorrection.from_mapping(correction.to_mapping(), 4)  # as identify writes it
    for name in ('weights', 'limit', 'inertia_limit'):
        np.testing.assert_array_equal(getattr(again, name), getattr(correction, name))


@pytest.mark.parametrize('bad', [{'weights': [[0.0] * FEATURES] * 3, 'limit': [0.1] * 4, 'speed_scale': 0.1},
                                 {'weights': [[0.0] * FEATURES] * 4, 'limit': [-1.0] * 4, 'speed_scale': 0.1},
                                 {'weights': [[0.0] * FEATURES] * 4, 'limit': [0.1] * 4},
                                 {'weights': [[np.nan] * FEATURES] * 4, 'limit': [0.1] * 4, 'speed_scale': 0.1},
                                 {'weights': [[0.0] * FEATURES] * 4, 'limit': [0.1] * 4, 'speed_scale': 0.1,
                                  'inertia_limit': [0.1] * 3}])
def test_a_malformed_learned_section_is_a_clear_error(bad):
    with pytest.raises(ConfigError, match='learned.torque'):
        TorqueCorrection.from_mapping(bad, 4, 'params.yaml')


def test_identify_learns_and_physics_only_does_not(tmp_path):
    """identify on a drive of the independent simulator whose Coulomb friction differs by
    direction (what the model lacks): the parameter file carries the correction, the pipeline uses it, physics_only ignores it and
    --physics-only writes none; the learned residual spread is lower."""
    import yaml
    from youbot_fdi.bench.independent_sim import simulate
    from youbot_fdi.cli.main import main
    from youbot_fdi.app.config import build_pipeline, configure
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.fdi.residuals import ResidualGenerator
    drive = [(0.3, 0.0, 0.0, 1.5), (-0.3, 0.0, 0.0, 1.5), (0.0, 0.25, 0.0, 1.5), (0.0, -0.25, 0.0, 1.5),
             (0.0, 0.0, 0.9, 1.5), (0.0, 0.0, -0.9, 1.5)] * 2
    # a direction-dependent Coulomb part well above the torque noise (0.06 N·m against about 0.13
    # RMS): at half of it the correction's gain was 0.5 %, on the edge of what learning keeps
    simulate(tmp_path / 'nominal', drive, seed=3, coulomb=0.1, coulomb_asymmetry=0.6)
    learned, physics = tmp_path / 'learned.yaml', tmp_path / 'physics.yaml'
    assert main(['identify', str(tmp_path / 'nominal'), '--output', str(learned)]) == 0
    assert main(['identify', str(tmp_path / 'nominal'), '--output', str(physics), '--physics-only']) == 0
    data = yaml.safe_load(learned.read_text())
    assert 'torque' in data['learned'] and 'learned' not in yaml.safe_load(physics.read_text())
    spread = data['identification']['learning']['residual_rms']
    assert spread['learned']['torque'] < spread['physics']['torque']
    assert build_pipeline(learned)[1].generator.correction is not None
    model, settings = configure(FdiSettings(physics_only=True), learned)
    assert ResidualGenerator(model, settings).correction is None
    assert build_pipeline(physics)[1].generator.correction is None


def test_the_learned_correction_lowers_the_spread_on_held_back_drives(tmp_path):
    """identify on one nominal drive of the independent simulator (current mode, its own RK4 plant;
    its commands act 4 ms late, so the current samples are not the torque of the interval: what
    the inertia part learns); replayed on other drives of the same robot (other seeds and another
    path), the corrected torque residual has less spread than the physics one, and no alarm is
    raised."""
    from dataclasses import replace

    from youbot_fdi.bench.independent_sim import simulate
    from youbot_fdi.cli.main import main
    from youbot_fdi.app.recordings import read_arrays
    from youbot_fdi.fdi.identify import run_generator
    from youbot_fdi.app.config import build_pipeline, configure
    from youbot_fdi.app.replay import replay_recording
    from youbot_fdi.settings import load_settings
    from youbot_fdi.fdi.settings import FdiSettings
    drive = [(0.3, 0.0, 0.0, 1.5), (0.0, 0.25, 0.0, 1.5), (0.0, 0.0, 0.9, 1.5), (0.2, -0.2, 0.0, 1.5),
             (-0.25, 0.1, -0.5, 1.5), (0.0, 0.0, 0.0, 0.5)]
    simulate(tmp_path / 'nominal', drive * 2, seed=1, mode='effort')
    params = tmp_path / 'params.yaml'
    assert main(['identify', str(tmp_path / 'nominal'), '--output', str(params)]) == 0
    assert build_pipeline(params)[1].generator.correction is not None
    model, settings = configure(load_settings(FdiSettings, 'fdi'), params)
    variants = {'learned': settings, 'physics': replace(settings, physics_only=True)}
    for seed, path in ((5, drive), (6, [(0.15, 0.15, 0.4, 2.0), (-0.3, 0.0, 0.0, 2.0), (0.0, -0.2, -0.8, 2.0)])):
        simulate(tmp_path / f'held_back{seed}', path, seed=seed, mode='effort')
        arrays = read_arrays(tmp_path / f'held_back{seed}', model)
        spread = {name: np.sqrt(np.nanmean(run_generator(model, arrays, variant).values['torque'] ** 2))
                  for name, variant in variants.items()}
        assert spread['learned'] < 0.97 * spread['physics']  # 5-6 % here
        assert [e for e in replay_recording(build_pipeline(params)[1], tmp_path / f'held_back{seed}').events
                if e.level == 'ERROR'] == []


def test_the_correction_holds_only_in_the_range_calibration_saw():
    """identify records each wheel's speed and acceleration range; outside it (widened by the
    margin) that wheel's correction is 0 (physics only), inside it is applied; a wheel only
    checks what it keeps (no inertia part: any acceleration is seen); the file round-trips."""
    rng = np.random.default_rng(4)
    truth = np.array([[0.05, 0.03, 0.002, 0.0], [0.0, 0.0, 0.0, -0.002],
                      [0.04, 0.0, 0.0, 0.001], [0.05, 0.0, 0.001, 0.0]])
    speed, acceleration, residual = synthetic(rng, truth)  # speeds within +-6 rad/s
    correction, _ = fit_torque_correction(speed, acceleration, residual, SCALE, torque_floor=0.01)
    np.testing.assert_allclose(correction.speed_range, [[speed[:, w].min(), speed[:, w].max()]
                                                        for w in range(4)])
    assert correction.acceleration_range.shape == (4, 2)
    read = TorqueCorrection.from_mapping(correction.to_mapping(), 4)
    np.testing.assert_allclose(read.speed_range, correction.speed_range)
    from dataclasses import replace
    margin = replace(read, range_margin=0.1)
    inside, fast = np.full(4, 3.0), np.array([3.0, 9.0, 9.0, 3.0])  # 9 rad/s > 6 + 10 % of 12
    still = np.zeros(4)
    friction, inertial, seen = margin.applied(fast, still)
    # Wheel 1 keeps no friction part: its speed is not checked; wheel 2 does: physics only.
    assert seen.tolist() == [True, True, False, True]
    assert friction[2] == 0.0 and friction[0] == margin.friction(fast)[0] != 0.0
    assert wheel_mask(seen) == 4.0 and masked_wheels(wheel_mask(seen), 4) == [2]
    assert margin.applied(np.full(4, 6.5), still)[2].all()  # within the margin
    hard = np.array([0.0, 1e4, 0.0, 0.0])  # wheel 1's inertia part: outside; wheel 0 has none
    assert margin.seen(inside, hard).tolist() == [True, False, True, True]
    np.testing.assert_array_equal(wheel_mask(np.stack([seen, seen])), [4.0, 4.0])
    # A file written before the ranges: every operating point is seen.
    old = {k: v for k, v in correction.to_mapping().items() if not k.endswith('_range')}
    assert TorqueCorrection.from_mapping(old, 4).seen(np.full(4, 1e3), np.full(4, 1e6)).all()
    with pytest.raises(ConfigError, match='speed_range'):
        TorqueCorrection.from_mapping({**correction.to_mapping(), 'speed_range': [[1.0, 0.0]] * 4}, 4)


def test_a_recording_outside_the_calibrated_range_falls_back_and_warns(tmp_path):
    """identify on a slow drive of the independent simulator (current mode: it learns an inertia
    part); a faster drive leaves the calibrated range: a WARN unseen_operating_point (no wheel,
    the detail naming the wheels), the residual rows outside flagged, an OK once back inside,
    and no alarm. The slow drive itself raises no such WARN."""
    from youbot_fdi.bench.independent_sim import simulate
    from youbot_fdi.cli.main import main
    from youbot_fdi.app.config import build_pipeline
    from youbot_fdi.app.replay import replay_recording
    from youbot_fdi.faults import UNSEEN_OPERATING_POINT
    slow = [(0.15, 0.0, 0.0, 1.5), (0.0, 0.12, 0.0, 1.5), (0.0, 0.0, 0.45, 1.5), (0.1, -0.1, 0.0, 1.5),
            (-0.12, 0.05, -0.25, 1.5), (0.0, 0.0, 0.0, 0.5)] * 2
    simulate(tmp_path / 'slow', slow, seed=1, mode='effort')
    params = tmp_path / 'params.yaml'
    assert main(['identify', str(tmp_path / 'slow'), '--output', str(params)]) == 0
    assert build_pipeline(params)[1].generator.correction is not None
    fast = [(0.1, 0.0, 0.0, 2.0), (0.0, 0.0, 0.0, 0.5), (0.0, 0.0, 1.6, 1.0), (0.0, 0.0, 0.0, 2.5),
            (0.1, 0.0, 0.0, 2.0)]
    simulate(tmp_path / 'fast', fast, seed=2, mode='effort')
    pipeline = build_pipeline(params, keep_frames=True)[1]
    events = replay_recording(pipeline, tmp_path / 'fast').events
    unseen = [e for e in events if e.fault == UNSEEN_OPERATING_POINT]
    assert [e.level for e in unseen][:2] == ['WARN', 'OK'] and unseen[0].wheel is None
    assert 'beyond what calibration covered' in unseen[0].detail and 'without the learned correction' in unseen[0].detail
    assert not [e for e in events if e.level == 'ERROR']
    frames = pipeline.residuals()
    outside = frames.outside_calibration > 0
    assert outside.any() and not outside.all()
    assert unseen[0].stamp == frames.stamp[np.flatnonzero(outside)[0]]
    assert not [e for e in replay_recording(build_pipeline(params)[1], tmp_path / 'slow').events
                if e.fault == UNSEEN_OPERATING_POINT]
    # The replay report shows the residual, its bound and the learned part against the speed.
    report = tmp_path / 'report'
    assert main(['replay', str(tmp_path / 'fast'), '--params', str(params), '--events',
                 str(tmp_path / 'events.jsonl'), '--report', str(report)]) == 0
    assert (report / 'operating_point.png').stat().st_size > 10_000
    assert 'operating_point.png' in (report / 'index.html').read_text()
