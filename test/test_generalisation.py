"""Diagnosis on data the project did not make: the clock rule, robust bound learning, evidence
accumulation, common-mode (load) rejection, frozen readings, and the real Robotino recordings."""
from dataclasses import replace
import math

import numpy as np
import pytest

from youbot_fdi.bench.independent_sim import simulate
from youbot_fdi.fdi.decision import DecisionMaker
from youbot_fdi.fdi.observer import signed_torque
from youbot_fdi.app.config import build_pipeline, load_residual_data, residual_data_for
from youbot_fdi.app.replay import replay_recording
from youbot_fdi.fdi.pipeline import FdiPipeline
from youbot_fdi.fdi.residuals import ResidualGenerator
from youbot_fdi.samples import message_time
from youbot_fdi.fdi.settings import FdiSettings
from youbot_fdi.model.profile import load_model

from frames import torque_frame

# `make check` (marker fast, conftest.py) takes every test here but these: identifications (the
# ``calibrated`` fixture is one, half a minute on a slow day) and the real recordings, which stay
# in `make test`.
FAST_EXCEPT = ('test_real_robotino_runs_convert_and_a_frozen_encoder_is_found',
               'test_commands_stamped_before_with_or_after_their_samples_give_no_false_alarm',
               'test_identify_reports_the_coverage_of_its_bounds',
               'test_the_contact_law_explains_real_omni_wheel_currents_better',
               'test_identify_learns_a_negative_delay_for_commands_stamped_late',
               'test_a_frozen_encoder_is_found_at_a_low_rate',
               'test_a_surface_change_on_every_wheel_is_a_warning_not_a_fault',
               'test_one_wheel_departing_from_the_others_still_alarms',
               'test_re_sent_messages_are_missing_data_not_a_wheel_fault')

DRIVE = [(0.3, 0.0, 0.0, 1.5), (0.0, 0.25, 0.0, 1.5), (0.0, 0.0, 0.9, 1.5), (0.2, -0.2, 0.0, 1.5),
         (-0.25, 0.1, -0.5, 1.5), (0.0, 0.0, 0.0, 0.5)]


@pytest.fixture(scope='module')
def model():
    return load_model('youbot')


def _calibrate(root, stamping='before'):
    """identify on a nominal drive of the independent simulator (velocity mode)."""
    from youbot_fdi.cli.main import main
    simulate(root / 'nominal', DRIVE * 2, seed=1, stamping=stamping)
    params = root / 'params.yaml'
    assert main(['identify', str(root / 'nominal'), '--output', str(params)]) == 0
    return root, params


@pytest.fixture(scope='module')
def calibrated(tmp_path_factory):
    return _calibrate(tmp_path_factory.mktemp('independent'))


def errors(path, params):
    return [e for e in replay_recording(build_pipeline(params)[1], path).events if e.level == 'ERROR']


# ---------------------------------------------------------------------- the clock rule
def test_message_time_is_the_header_stamp_or_else_the_receive_time():
    np.testing.assert_array_equal(message_time(np.array([5.0, 0.0]), np.array([7.0, 8.0])), [5.0, 8.0])


def test_a_command_is_in_force_by_its_stamp_not_by_when_it_arrived(model):
    """A command stamped with its sample is in force at that sample whether it arrived before it
    or after it (the replay sees the whole chunk); one stamped later is not."""
    settings = FdiSettings()
    generator = ResidualGenerator(model, settings)
    from youbot_fdi.samples import CommandBatch
    commands = CommandBatch(np.array([1.0, 2.0]), np.array([True, True]),
                            np.array([[1.0, 1.0, 1.0, 1.0], [2.0, 2.0, 2.0, 2.0]]))
    stamps = np.array([1.0, 1.1, 2.0, 2.01])
    _, target, _ = generator.observer._commands_in_force(stamps, commands, np.zeros(4, dtype=int))
    signs = model.kinematics.drive_signs
    np.testing.assert_allclose(target, signs * np.array([[1.0] * 4, [1.0] * 4, [2.0] * 4, [2.0] * 4]))


@pytest.mark.parametrize('timeout', [0.25, math.inf])
def test_a_command_held_by_the_driver_stays_in_force_none_before_the_first(model, timeout):
    """With the shim's watchdog (0.25 s) a command 0.5 s old means zero speed; with a driver that
    holds its last command (command_timeout inf) it stays in force. Before the first command
    there is none: zero speed either way (not the command to come)."""
    from youbot_fdi.samples import CommandBatch
    generator = ResidualGenerator(model, replace(FdiSettings(), command_timeout=timeout))
    commands = CommandBatch(np.array([1.0]), np.array([True]), np.array([[1.0, 1.0, 1.0, 1.0]]))
    stamps = np.array([0.5, 1.0, 1.1, 1.5])
    _, target, _ = generator.observer._commands_in_force(stamps, commands, np.zeros(4, dtype=int))
    held = 1.0 if math.isinf(timeout) else 0.0
    expected = np.array([[0.0] * 4, [1.0] * 4, [1.0] * 4, [held] * 4]) * model.kinematics.drive_signs
    np.testing.assert_allclose(target, expected)


def test_the_latest_command_sent_is_known_while_the_delay_holds_it_back(model):
    """With a 0.1 s input delay, a command stamped at 1.05 s is sent but not yet acting at
    1.1 s: the command in force is the one of 1.0 s, the latest the one of 1.05 s. Before any
    command acts (1.02 s) the target is zero speed and the latest the one of 1.0 s; once the
    newest acts (1.2 s) both agree. A command of the other mode is not the latest of this one."""
    from youbot_fdi.samples import CommandBatch
    generator = ResidualGenerator(model, replace(FdiSettings(), input_delay=0.1))
    commands = CommandBatch(np.array([1.0, 1.05, 1.3]), np.array([True, True, False]),
                            np.array([[1.0] * 4, [2.0] * 4, [0.1] * 4]))
    stamps = np.array([1.02, 1.1, 1.2, 1.35])
    _, target, latest = generator.observer._commands_in_force(stamps, commands, np.zeros(4, dtype=int))
    signs = model.kinematics.drive_signs
    np.testing.assert_allclose(target, signs * np.array([[0.0] * 4, [1.0] * 4, [2.0] * 4, [2.0] * 4]))
    np.testing.assert_allclose(latest, signs * np.array([[1.0] * 4, [2.0] * 4, [2.0] * 4, [2.0] * 4]))


@pytest.mark.parametrize('stamping', ['before', 'with', 'after'])
def test_commands_stamped_before_with_or_after_their_samples_give_no_false_alarm(stamping, tmp_path):
    """A robot stamps its commands one way; calibrated on its own recording, another drive of it
    raises nothing, and a fault is still found on its wheel."""
    _, params = _calibrate(tmp_path, stamping)
    simulate(tmp_path / 'drive', DRIVE, seed=5, stamping=stamping)
    assert errors(tmp_path / 'drive', params) == []
    start = simulate(tmp_path / 'fault', DRIVE, seed=5, stamping=stamping, fault='stuck', wheel=3,
                     fault_time=2.0)
    alarms = errors(tmp_path / 'fault', params)
    assert alarms and alarms[0].wheel == 'wheel_joint_br' and alarms[0].stamp >= start + 2.0


def test_identify_learns_a_negative_delay_for_commands_stamped_late(tmp_path, model):
    """Commands stamped a sample after the samples they produce: the input delay comes out at or
    below zero and the command path still predicts the wheels."""
    from youbot_fdi.app.recordings import read_arrays
    from youbot_fdi.fdi.identify import delay_grid, fit_input_delay
    simulate(tmp_path / 'late', DRIVE, seed=3, stamping='after', delay=0.0)
    simulate(tmp_path / 'early', DRIVE, seed=3, stamping='before', delay=0.0)
    late = fit_input_delay(model, read_arrays(tmp_path / 'late', model), delay_grid(0.02))[0]
    early = fit_input_delay(model, read_arrays(tmp_path / 'early', model), delay_grid(0.02))[0]
    assert late <= 0.0 < early + 0.005
    assert early - late == pytest.approx(0.02, abs=0.0051)  # a whole sample apart


def test_recordings_without_header_stamps_use_the_receive_time(tmp_path, model):
    from youbot_fdi.bag.reader import RecordingReader
    from youbot_fdi.bag.writer import RecordingWriter
    with RecordingWriter(tmp_path / 'r', model.wheel_names) as writer:
        for k in range(5):
            writer.wheel_command(100.0 + 0.01 * k, 'velocity', np.ones(4), header_stamp=None)
            writer.joint_state(100.0 + 0.01 * k, np.zeros(4), np.zeros(4), np.zeros(4), header_stamp=None)
    with RecordingReader(tmp_path / 'r', model.wheel_names) as reader:
        stamps = [s.stamp for s in reader.samples()]
    assert stamps == pytest.approx(np.repeat(100.0 + 0.01 * np.arange(5), 2))


# ---------------------------------------------------------------------- robust bounds
def test_quantile_bounds_ignore_an_outlier_that_a_maximum_would_learn():
    from youbot_fdi.fdi.identify import quantile_fit
    rng = np.random.default_rng(0)
    speed = rng.uniform(0, 10, 4000)
    residual = np.abs(rng.normal(0, 0.1 + 0.05 * speed))
    features = np.column_stack([np.ones_like(speed), speed])
    clean = quantile_fit(features, residual, 0.99)
    residual[17] = 50.0  # one late sample
    spoiled = quantile_fit(features, residual, 0.99)
    np.testing.assert_allclose(spoiled, clean, rtol=0.05)
    assert clean[1] > 0.05  # the bound grows with speed (operating point)
    coverage = np.mean(residual <= features @ spoiled)
    assert 0.985 <= coverage <= 0.995


def test_identify_reports_the_coverage_of_its_bounds(calibrated, capsys):
    from youbot_fdi.cli.main import main
    root, _ = calibrated
    assert main(['identify', str(root / 'nominal'), '--output', str(root / 'again.yaml')]) == 0
    out = capsys.readouterr().out
    assert 'nominal samples inside: torque' in out and 'sample interval 20.0 ms' in out


# ---------------------------------------------------------------------- evidence accumulation
def _first_alarm(model, scores):
    decision = DecisionMaker(model.wheel_names, FdiSettings(), load_residual_data())
    for k, score in enumerate(scores):
        if any(e.level == 'ERROR' for e in decision.update(torque_frame(model, 10.0 + 0.01 * k, score))):
            return k
    return None


def test_a_small_persistent_excess_adds_up_to_an_alarm(model):
    settings = FdiSettings()
    k = _first_alarm(model, [1.3] * 40)
    expected = math.ceil(settings.family_thresholds[0] / (1.3 - settings.evidence_drift)) - 1
    assert k == expected
    assert _first_alarm(model, [0.95] * 400) is None  # inside the bound: never


def test_a_transient_within_the_floor_is_not_an_alarm(model):
    """The dynamic families' floor (config/fdi.yaml) is the evidence of a model error at 1.5
    bounds for 0.1 s, a transient beyond calibration: (1.5 - drift) x 0.1 s / evidence_interval
    = 5. At 100 Hz, nine such samples raise nothing, a tenth alarms."""
    settings = FdiSettings()
    samples = round(settings.family_thresholds[0] / (1.5 - settings.evidence_drift))
    assert samples * settings.evidence_interval == pytest.approx(0.1)
    assert _first_alarm(model, [1.5] * (samples - 1) + [0.3] * 50) is None
    assert _first_alarm(model, [1.5] * samples + [0.3] * 50) == samples - 1


def test_a_single_spike_is_not_an_alarm_and_a_large_fault_is_found_at_once(model):
    settings = FdiSettings()
    assert _first_alarm(model, [0.3] * 5 + [100.0] + [0.3] * 50) is None
    # capped at evidence_cap, a score adds cap - drift a sample: over the threshold (5) at its third
    samples = math.ceil(settings.family_thresholds[0] / (settings.evidence_cap - settings.evidence_drift))
    assert samples == 3
    assert _first_alarm(model, [0.3] * 5 + [100.0] * 8) == 5 + samples - 1


def _events(model, scores, interval=0.01):
    decision = DecisionMaker(model.wheel_names, FdiSettings(), load_residual_data())
    return [(k, e) for k, score in enumerate(scores)
            for e in decision.update(torque_frame(model, 10.0 + interval * k, score))]


def test_a_start_from_rest_is_not_evidence_but_the_same_excess_later_is(model):
    """Leaving rest, wheels slip and break static friction until the base catches up (a real
    Robotino start on rubber: one wheel at twice its current for 0.15 s): the torque excess within
    breakaway_time after the last sample at rest adds no evidence; the same excess once the base
    rolls is an alarm, and so is one that outlasts the breakaway."""
    settings = FdiSettings()
    interval = 0.03  # the Robotino's rate
    breakaway = int(settings.breakaway_time / interval)  # samples after the last one at rest
    rest, excess = [(0.0, 0.0)] * 20, [(2.0, 2.0)] * breakaway

    def alarms(rows):
        decision = DecisionMaker(model.wheel_names, settings, load_residual_data())
        return [k for k, (speed, score) in enumerate(rows)
                for e in decision.update(torque_frame(model, 10.0 + interval * k, score, speed=speed))
                if e.level == 'ERROR']

    rolling = [(2.0, 0.3)] * 100
    assert alarms(rest + excess + rolling) == []
    assert alarms(rest + rolling[:50] + excess + rolling[50:]) != []  # the same, once rolling
    assert alarms(rest + excess + [(2.0, 2.0)] * 5 + rolling) != []  # longer than a breakaway
    assert alarms(rest + excess + rest + excess + rolling) == []  # each start from rest


def test_a_torque_shift_inside_the_bound_is_found_and_held(model):
    """A wheel's torque residual that steps by 0.8 of its bound and stays there never exceeds the
    bound, yet departs from its recent level: found after about threshold / (0.8 - drift)
    samples, and held (the level does not learn a fault) until the shift ends."""
    settings = FdiSettings()
    steady, shifted = [0.1] * 1000, [0.9] * 1000  # 10 s: the level's memory is full
    events = _events(model, steady + shifted + steady)
    assert [(e.level, e.wheel) for _, e in events] == [('ERROR', 'wheel_joint_fl'), ('OK', 'wheel_joint_fl')]
    (raised, _), (cleared, _) = events
    expected = math.ceil(settings.shift_threshold / (0.8 - settings.shift_drift)) - 1
    assert expected <= raised - len(steady) <= 1.3 * expected  # the level follows a little meanwhile
    assert cleared > len(steady) + len(shifted)  # held through 10 s of the fault
    # the ceiling drains quickly; the episode heals heal_time later (frames every 10 ms)
    assert cleared - len(steady) - len(shifted) <= (settings.release_time + settings.heal_time) / 0.01 + 30


def test_a_slow_drift_of_the_same_size_is_not_a_fault(model):
    """Friction that changes as slowly as the level follows (here 0.8 bound over 30 s) is not a
    shift, nor is a step back and forth shorter than the evidence needs."""
    drift = list(0.1 + 0.8 * np.linspace(0.0, 1.0, 3000))
    assert _events(model, [0.1] * 200 + drift + [0.9] * 500) == []
    assert _events(model, ([0.1] * 50 + [0.9] * 8) * 20) == []


def test_a_position_repeating_while_the_wheel_turns_is_a_frozen_sensor(model):
    decision = DecisionMaker(model.wheel_names, FdiSettings(), load_residual_data())
    events = []
    for k in range(5):
        events += decision.update(torque_frame(model, 10.0 + 0.03 * k, 0.0, position_frozen=k + 1))
    assert [(e.level, e.wheel, e.fault) for e in events] == [('ERROR', 'wheel_joint_fl', 'encoder_freeze')]


def test_a_frozen_encoder_is_found_at_a_low_rate(tmp_path, model, calibrated):
    """The independent simulator's 50 Hz readings freeze on one wheel: found on that wheel
    within a few samples."""
    _, params = calibrated
    start = simulate(tmp_path / 'freeze', DRIVE, fault='encoder_freeze', wheel=1, fault_time=2.0, seed=7)
    alarms = errors(tmp_path / 'freeze', params)
    assert alarms and {e.wheel for e in alarms} == {'wheel_joint_fr'}
    assert 0.0 <= alarms[0].stamp - (start + 2.0) <= 0.1


# ---------------------------------------------------------------------- common-mode rejection
def test_a_surface_change_on_every_wheel_is_a_warning_not_a_fault(tmp_path, calibrated):
    _, params = calibrated
    simulate(tmp_path / 'surface', DRIVE, seed=9, surface_factor=1.8, surface_time=3.0)
    events = replay_recording(build_pipeline(params)[1], tmp_path / 'surface').events
    assert [e for e in events if e.level == 'ERROR'] == []
    warnings = [e for e in events if e.level == 'WARN']
    assert warnings and warnings[0].fault == 'load_change' and warnings[0].wheel is None
    assert 'surface or load changed' in warnings[0].detail


def test_one_wheel_departing_from_the_others_still_alarms(tmp_path, calibrated):
    _, params = calibrated
    start = simulate(tmp_path / 'one', DRIVE, seed=9, fault='friction', wheel=2, fault_time=3.0)
    alarms = errors(tmp_path / 'one', params)
    assert alarms and alarms[0].wheel == 'wheel_joint_bl' and alarms[0].stamp >= start + 3.0


def test_a_second_wheel_failing_later_is_not_shared_with_the_first(tmp_path, model):
    """A wheel in alarm since long ago does not make a later fault on another wheel a "shared"
    change (half the wheels of four): both are found, each on its wheel."""
    from youbot_fdi.model.scenario import load_script
    from youbot_fdi.tmcm.recordings import record_drive
    truth = record_drive(tmp_path / 'two', model, load_script(duration=12.0)[1], fault='friction',
                         wheel='wheel_joint_fl', fault_time=1.0,
                         more_faults=[('stuck', 'wheel_joint_br', 6.0)])
    alarms = errors(tmp_path / 'two', None)
    first = {w: min(e.stamp for e in alarms if e.wheel == w) for w in {e.wheel for e in alarms}}
    assert set(first) == {'wheel_joint_fl', 'wheel_joint_br'}
    assert first['wheel_joint_br'] >= truth.onset + 5.0 > first['wheel_joint_fl'] >= truth.onset


def test_the_load_factor_is_the_part_every_wheel_shares(model):
    generator = ResidualGenerator(model, FdiSettings(torque_sigma=0.01))
    friction = np.array([0.2, 0.2, 0.2, 0.2])
    shares = np.ones((1, 4))  # all Coulomb
    both = np.concatenate([[1.5, 1.3, 1.4, 1.6] * friction, friction, 0.0 * friction])[None]
    assert float(generator.observer._load_factor(both, 1.0, shares)[0][0]) == pytest.approx(1.45)  # the median
    one = np.concatenate([[2.0, 1.0, 1.0, 1.0] * friction, friction, 0.0 * friction])[None]
    assert float(generator.observer._load_factor(one, 1.0, shares)[0][0]) == pytest.approx(1.0)  # one wheel: a fault


# ---------------------------------------------------------------------- the real recordings
robotino = pytest.importorskip('youbot_fdi.bench.robotino')
needs_data = pytest.mark.skipif(robotino.data_dir() is None,
                                reason='the Robotino recordings (../shared/real_data/robotino) are absent')


@needs_data
def test_real_robotino_runs_convert_and_a_frozen_encoder_is_found(tmp_path):
    """A green-surface calibration, then a gray-surface run (another floor covering) with one
    wheel's encoder frozen half-way: found on that wheel; the same run untouched: no alarm."""
    from youbot_fdi.cli.main import main
    root = robotino.data_dir()
    model = load_model(robotino.PROFILE)
    calibration = [robotino.read_run(root / 'green_surface' / f'exp{nn:02d}.csv') for nn in (0, 18, 36, 54)]
    robotino.write_recording(calibration, tmp_path / 'cal', model)
    params = tmp_path / 'params.yaml'
    assert main(['identify', str(tmp_path / 'cal'), '--profile', 'robotino', '--output', str(params)]) == 0
    run = robotino.read_run(root / 'gray_surface' / 'exp24.csv')
    robotino.write_recording([run], tmp_path / 'clean', model)
    assert errors(tmp_path / 'clean', params) == []
    onset = len(run) // 2
    start = robotino.write_recording([robotino.inject(run, 'encoder_freeze', 0, onset)],
                                     tmp_path / 'frozen', model)[0]
    alarms = errors(tmp_path / 'frozen', params)
    assert alarms and alarms[0].wheel == 'robotino_wheel_1'
    assert 0.0 <= alarms[0].stamp - (start + run.time[onset] - run.time[0]) <= 0.3


@needs_data
def test_the_contact_law_explains_real_omni_wheel_currents_better(tmp_path, monkeypatch):
    """Real Robotino currents depend on the direction the contact moves, not on the wheel's speed
    alone: identified on green runs at 0° and 90° at every speed, the contact law (roller_friction_ratio > 0) is
    chosen, and on held-out green runs in other directions (15°, 45°, 75° at 0.2 m/s) its torque
    residual is smaller than per-wheel Coulomb friction's, fitted on the same recording."""
    from youbot_fdi.app.recordings import identify_recording, read_arrays
    from youbot_fdi.fdi import identify as identification
    from youbot_fdi.model.profile import PlatformModel
    from youbot_fdi.settings import load_settings
    root, model = robotino.data_dir(), load_model(robotino.PROFILE)
    green = root / 'green_surface'
    robotino.write_recording([robotino.read_run(green / f'exp{nn:02d}.csv') for nn in (0, 18, 72, 90, 144, 162)],
                             tmp_path / 'cal', model)
    robotino.write_recording([robotino.read_run(green / f'exp{nn:02d}.csv') for nn in (75, 81, 87)],
                             tmp_path / 'held_out', model)
    settings = load_settings(FdiSettings, 'fdi')

    def held_out_rms(ratios):
        monkeypatch.setattr(identification, 'ROLLER_RATIOS', ratios)
        result = identify_recording(tmp_path / 'cal', model, settings, fit_gains=False, learn=False)
        fitted = PlatformModel(result.profile)
        arrays = read_arrays(tmp_path / 'held_out', fitted)
        torque = identification.run_generator(fitted, arrays, settings).values['torque']
        return (result.profile.dynamics.roller_friction_ratio, float(np.sqrt(np.nanmean(torque ** 2))),
                result.fdi['contact_share_floor'])

    ratio, contact, floor = held_out_rms(identification.ROLLER_RATIOS)
    _, per_wheel, no_floor = held_out_rms(np.array([0.0]))
    assert ratio > 0.0
    assert contact < 0.85 * per_wheel
    # the range the law was calibrated on: wheels meeting the motion at 0°, 30°, 60° (not 75°)
    assert 0.2 < floor < 0.9 and no_floor == 0.0


def test_the_observer_explains_the_rollers_drag_of_a_sideways_drive(model):
    """Driving sideways at a steady speed, each wheel needs its viscous and Coulomb friction and
    the rollers' drag, which brakes one diagonal and helps the other: the observer's explained
    torque is exactly that (the exact discretisation's ``Gamma^-1 (I - Phi) = D`` at a steady
    speed), and a measured torque equal to it leaves no torque residual."""
    from youbot_fdi.fdi.observer import ModelObserver
    from youbot_fdi.model.profile import PlatformModel
    from youbot_fdi.samples import JointBatch
    dragging = PlatformModel(replace(model.profile, dynamics=replace(model.dynamics.parameters,
                                                                   roller_drag=0.05)))
    dynamics, signs = dragging.dynamics, dragging.kinematics.drive_signs
    speeds = dragging.kinematics.inverse(np.array([0.0, 0.3, 0.0]))  # kinematic convention
    drag = dynamics.roller_drag_torque(speeds)
    assert np.all(np.abs(drag) > 0.03) and drag.min() < 0.0 < drag.max()  # brakes some, helps others
    steady = speeds @ dynamics.friction_matrix.T + dynamics.coulomb_torque(speeds)
    rows = 30
    stamps = 0.01 * np.arange(rows)
    joints = JointBatch(stamps, np.outer(stamps, signs * speeds), np.tile(signs * speeds, (rows, 1)),
                        np.tile(signs * steady, (rows, 1)))
    predictions = ModelObserver(dragging, FdiSettings()).update_batch(joints)
    kept = ~predictions.restart
    np.testing.assert_allclose(predictions.explained[kept], np.tile(steady, (kept.sum(), 1)), rtol=1e-6)
    batch = ResidualGenerator(dragging, FdiSettings()).update_batch(joints)
    np.testing.assert_allclose(batch.values['torque'], 0.0, atol=1e-6)


def test_the_rollers_drag_a_floor_adds_is_measured_from_what_the_wheels_share(model):
    """Driving forward and a little sideways, a floor that drags the mecanum rollers with
    D = 0.05 N·m the model does not have leaves ``D shape`` unexplained: one diagonal braked, the
    other helped (against the wheels' speeds: no load factor). Every voting wheel's smoothed
    ratio of residual to pattern is D, so the shared drag is D; a fault on one wheel does not move
    it (a median of four), nor let any wheel stand off it (the others agree); a pattern of the
    opposite sign is no drag (it dissipates: 0); a base that slips beyond calibration does not
    vote; omni wheels have no pattern."""
    from youbot_fdi.fdi.observer import ModelObserver
    speeds = model.kinematics.inverse(np.array([0.3, 0.05, 0.0]))  # kinematic convention
    shape = model.dynamics.roller_drag_shape(speeds)
    assert np.any(np.sign(shape) != np.sign(speeds))  # helps a diagonal: not friction's pattern
    rows, drag, fault = 200, 0.05, np.array([0.2, 0.0, 0.0, 0.0])  # [N·m]
    keep = np.full(rows, np.exp(-0.01 / FdiSettings().load_time_constant))
    friction, inertial = np.full((rows, 4), 0.1), np.zeros((rows, 4))

    def shared(residual, settings=FdiSettings(), profile=model):
        observer = ModelObserver(profile, settings)
        velocity = np.tile(speeds, (rows, 1))
        torque, spread = observer._shared_drag(
            velocity, profile.dynamics.roller_drag_shape(velocity), np.tile(residual, (rows, 1)),
            inertial, friction, keep)
        estimate = torque @ shape / (shape @ shape)  # the size: the torque is size x pattern
        np.testing.assert_allclose(torque, estimate[:, None] * shape, rtol=1e-12, atol=1e-15)
        spreads.append(spread[-1])
        return estimate

    spreads = []
    estimate = shared(drag * shape)
    assert estimate[0] == 0.0  # one row's vote is not yet a quarter of the pattern
    assert estimate[-1] == pytest.approx(drag, rel=1e-12)
    assert shared(drag * shape + fault)[-1] == pytest.approx(drag, rel=1e-12)
    # every voter agrees, and beside the fault the three others do: no wheel may stand off it
    np.testing.assert_allclose(spreads, 0.0, atol=1e-12)
    assert np.all(shared(-drag * shape) == 0.0)
    never_slipped = replace(FdiSettings(), calibrated_slip=0.0, speed_sigma=0.0)  # limit 0
    assert np.all(shared(drag * shape, never_slipped) == 0.0)  # rounding's slip is beyond it
    assert not load_model('robotino').dynamics.drag_share.any()  # omni: nothing to measure


def test_unsigned_effort_is_signed_by_the_explained_torque(model):
    """A profile whose effort is a magnitude: the generator signs it, so a braking wheel's torque
    is negative as it is physically."""
    from dataclasses import replace
    from youbot_fdi.model.profile import PlatformModel
    unsigned = PlatformModel(replace(model.profile, drive=replace(model.drive, signed_effort=False)))
    generator = ResidualGenerator(unsigned, FdiSettings())
    signs = signed_torque(np.array([0.5, 0.5]), np.array([-0.2, 0.3]), generator.observer.signed_effort)
    assert signs.tolist() == [-0.5, 0.5]
    assert FdiPipeline(unsigned, FdiSettings(), residual_data_for(unsigned, FdiSettings())).generator.observer.signed_effort is False


# ---------------------------------------------------------------------- re-sent messages
def _batch(rows):
    """A JointBatch of two wheels from rows (position, speed, effort) of equal values per wheel,
    sampled every 20 ms."""
    from youbot_fdi.samples import JointBatch
    values = np.array(rows, dtype=float)
    return JointBatch(0.02 * np.arange(len(rows)), *(np.repeat(values[:, [k]], 2, axis=1) for k in range(3)))


def test_a_message_re_sent_unchanged_while_the_base_moves_carries_no_fresh_data():
    from youbot_fdi.samples import RepeatedMessages
    moving = _batch([(0.0, 1.0, 0.2), (0.02, 1.0, 0.2), (0.02, 1.0, 0.2), (0.02, 1.0, 0.2), (0.06, 1.0, 0.2)])
    repeated = RepeatedMessages()
    assert repeated.fresh(moving).tolist() == [True, True, False, False, True]
    assert repeated.count == 2
    standing = _batch([(0.5, 0.0, 0.0)] * 4)  # a base standing still repeats itself legitimately
    assert RepeatedMessages().fresh(standing).all()
    one_wheel = _batch([(0.0, 1.0, 0.2), (0.02, 1.0, 0.2)])
    one_wheel.position[1, 1] = 0.0  # wheel 2's reading repeats, wheel 1's does not: its fault
    assert RepeatedMessages().fresh(one_wheel).all()
    # the state carries over blocks, and one sample at a time gives the same
    split = RepeatedMessages()
    assert split.fresh(moving.rows(0, 2)).tolist() + split.fresh(moving.rows(2, 5)).tolist() == \
        [True, True, False, False, True]
    single = RepeatedMessages()
    assert [single.fresh_sample(moving.sample(k)) for k in range(5)] == [True, True, False, False, True]


def _resend(chunks, start, count):
    """The chunks with joint rows ``start`` .. ``start + count`` (over the recording) replaced by
    copies of row ``start - 1``, stamps kept: a logger re-sending its last message."""
    from youbot_fdi.samples import JointBatch
    out, offset, last = [], 0, None
    for chunk in chunks:
        j = chunk.joints
        arrays = [a.copy() for a in (j.position, j.velocity, j.effort)]
        for k in range(max(start, offset), min(start + count, offset + len(j))):
            for a, previous in zip(arrays, last if k == offset else (a[k - 1 - offset] for a in arrays)):
                a[k - offset] = previous
        out.append(replace(chunk, joints=JointBatch(j.stamp, *arrays)))
        last = [a[-1].copy() for a in arrays]
        offset += len(j)
    return out


@pytest.mark.parametrize('count, base_silent', [(4, False), (40, True)])
def test_re_sent_messages_are_missing_data_not_a_wheel_fault(calibrated, count, base_silent):
    """Every wheel's readings re-sent for a few samples while the base drives: no alarm (the
    Robotino's logger does this); for longer than the data timeout: the base's comm_loss, as a
    gap in /joint_states is, not a wheel fault."""
    from youbot_fdi.bag.reader import RecordingReader
    root, params = calibrated
    model, pipeline = build_pipeline(params)
    with RecordingReader(root / 'nominal', model.wheel_names) as reader:
        chunks = list(reader.chunks(size=64))
    start = 2 * 50 + 17  # in the second 1.5 s segment (driving sideways), 50 Hz
    events = [e for chunk in _resend(chunks, start, count) for e in pipeline.feed(chunk)]
    alarms = [e for e in events if e.level == 'ERROR']
    assert pipeline.repeated.count == count
    if base_silent:
        assert [(e.wheel, e.fault) for e in alarms] == [(None, "comm_loss")]
    else:
        assert alarms == []


# ---------------------------------------------------------------------- the contact law's range
def _contact_model(ratio):
    from youbot_fdi.model.profile import PlatformModel
    base = load_model('youbot')
    return PlatformModel(replace(base.profile, dynamics=replace(
        base.profile.dynamics, coulomb_friction=(0.3,) * 4, roller_friction_ratio=ratio)))


def test_a_wheel_outside_the_contact_laws_calibrated_range_is_allowed_the_shortfall():
    """Below the lowest rolling share seen in calibration the law is extrapolated: the torque
    bound allows the Coulomb level times the shortfall, the command bound what the loop's
    proportional gain leaves of it; nothing more without the law or inside its range than what
    every gliding roller is allowed (:func:`test_a_gliding_roller_is_allowed_its_coulomb_level`)."""
    from youbot_fdi.fdi.observer import ModelObserver
    from youbot_fdi.samples import JointBatch, JointSample
    speeds = np.array([[0.1, 4.0, 4.0, 0.1]])  # wheels 1 and 4 turn slowly while their contacts slide
    model = _contact_model(1.0)
    dyn = model.dynamics
    share = dyn.rolling_shares(speeds)[0]
    assert share[0] < 0.3 and share[1] > 0.6
    floor = 0.6
    glide = np.abs(dyn.coulomb_level(dyn.kinematics.roller_slide(speeds)))
    observer = ModelObserver(model, replace(FdiSettings(), contact_share_floor=floor))
    _, level, unseen = observer._coulomb(speeds)
    np.testing.assert_allclose(unseen[0] - glide[0], np.abs(level[0]) * np.maximum(0.0, floor - share))
    assert unseen[0, 0] > glide[0, 0] and unseen[0, 1] == glide[0, 1]
    np.testing.assert_array_equal(ModelObserver(model, FdiSettings())._coulomb(speeds)[2], glide)  # floor 0
    np.testing.assert_array_equal(ModelObserver(_contact_model(0.0), replace(
        FdiSettings(), contact_share_floor=floor))._coulomb(speeds)[2], glide)  # no contact law

    def bounds(settings):
        samples = [JointSample(0.01 * k, speeds[0] * 0.01 * k, speeds[0], 0.2 * np.sign(speeds[0]))
                   for k in range(60)]  # past the command path's start-up time
        generator = ResidualGenerator(model, settings)
        frames = [generator.update(sample) for sample in samples]
        batch = ResidualGenerator(model, settings).update_batch(JointBatch(
            np.array([x.stamp for x in samples]), *(np.array([getattr(x, f) for x in samples])
                                                    for f in ('position', 'velocity', 'effort'))))
        for family in ('torque', 'command'):  # one sample at a time and in a block alike
            np.testing.assert_allclose(batch.bounds[family][-1], frames[-1].bounds[family], rtol=1e-12)
        return frames[-1], generator.last_prediction

    wide, prediction = bounds(replace(FdiSettings(), contact_share_floor=floor))
    narrow, glided = bounds(FdiSettings())
    extra = np.abs(prediction.load_factor * prediction.unseen_friction) - np.abs(
        glided.load_factor * glided.unseen_friction)
    np.testing.assert_allclose(wide.bounds['torque'] - narrow.bounds['torque'], extra, atol=1e-12)
    compliance = 1.0 / (model.firmware.velocity_kp * model.drive.torque_per_amp)
    np.testing.assert_allclose(wide.bounds['command'] - narrow.bounds['command'], extra * compliance,
                               atol=1e-12)


def test_a_gliding_roller_is_allowed_its_coulomb_level():
    """A contact that slides along its roller's free direction (the two standing wheels of a
    diagonal drive, every wheel of a sideways one) may pass its wheel up to the Coulomb level of
    that slide, F_c tanh(|u| / v_s): unseen friction, at a standing wheel too; a wheel whose
    contact only rolls (driving straight ahead) is allowed nothing."""
    from youbot_fdi.fdi.observer import ModelObserver
    model = _contact_model(0.0)
    kinematics, dyn = model.kinematics, model.dynamics
    observer = ModelObserver(model, FdiSettings())
    ahead, sideways, diagonal = (kinematics.inverse(np.array(twist)) for twist in
                                 ((0.3, 0.0, 0.0), (0.0, 0.3, 0.0), (0.3, 0.3, 0.0)))
    np.testing.assert_allclose(observer._coulomb(ahead)[2], 0.0, atol=1e-12)
    slide = kinematics.roller_slide(sideways)
    assert np.all(np.abs(slide) > 1.0)  # every contact glides sideways
    np.testing.assert_allclose(observer._coulomb(sideways)[2],
                               0.3 * np.tanh(np.abs(slide) / dyn.parameters.coulomb_velocity_scale))
    standing = np.abs(diagonal) < 1e-9
    assert standing.sum() == 2
    assert np.all(observer._coulomb(diagonal)[2][standing] > 0.2)  # standing wheels, gliding rollers


def test_the_calibrated_range_warn_is_the_same_frame_by_frame_and_in_a_block(model):
    """The decision's WARN/OK of the learned correction's range: WARN at the first row outside,
    OK after unseen_release s back inside (not at every short return), the same one frame at a
    time and in one batch; reset ends it."""
    from dataclasses import replace as changed
    from youbot_fdi.fdi.residuals import ResidualBatch
    from youbot_fdi.faults import UNSEEN_OPERATING_POINT
    settings = FdiSettings()
    masks = [0.0] * 10 + [2.0] * 5 + [0.0] * 20 + [6.0] * 3 + [0.0] * 250
    frames = [changed(torque_frame(model, 10.0 + 0.01 * k, 0.1), outside_calibration=m)
              for k, m in enumerate(masks)]
    one = DecisionMaker(model.wheel_names, settings, load_residual_data())
    single = [e for f in frames for e in one.update(f)]
    block = DecisionMaker(model.wheel_names, settings, load_residual_data())
    batched = block.update_batch(ResidualBatch.concatenate([_batch_of(f) for f in frames]))
    assert [e.to_dict() for e in single] == [e.to_dict() for e in batched]
    # OK unseen_release after the last row outside, published heal_time later
    assert [(e.level, round(e.stamp, 2)) for e in single] == [
        ('WARN', 10.1), ('OK', round(10.37 + settings.unseen_release + settings.heal_time, 2))]
    assert single[0].fault == UNSEEN_OPERATING_POINT and 'fr' in single[0].detail
    again = DecisionMaker(model.wheel_names, settings, load_residual_data())
    again.update(frames[10])
    events, cleared = again.reset(11.0)
    assert [e.level for e in events] == ['OK'] and cleared == [f'base: {UNSEEN_OPERATING_POINT}']


def _batch_of(frame):
    """A one-row ResidualBatch of a ResidualFrame."""
    from youbot_fdi.fdi.residuals import ResidualBatch, ROW_ARRAYS
    defaults = ('torque_scale', 'torque_confirmed', 'friction_level')  # unset: what they stand for
    rows = {name: np.asarray([getattr(frame, name) if name != 'velocity_mode'
                              else frame.velocity_mode])
            for name in ROW_ARRAYS if name not in ('command_speed', *defaults)}
    rows.update({name: frame.signal(name)[None] for name in defaults})
    return ResidualBatch(values={f: v[None] for f, v in frame.values.items()},
                         bounds={f: b[None] for f, b in frame.bounds.items()},
                         command_speed=frame.velocity[None], **rows)


def test_a_firmware_scan_that_overflowed_counts_as_saturated(model):
    """An unstable loop (a prior's gains during identify) can overflow the linear prefix scan of
    the firmware loop to inf and NaN; NaN compares False with every limit, so such rows are
    flagged saturated by being non-finite and stepped one by one (clipped) instead."""
    from youbot_fdi.fdi.observer import ModelObserver
    observer = ModelObserver(model, FdiSettings())
    n = observer.n
    before = np.zeros((3, 2 * n))
    after = np.zeros((3, 2 * n))
    after[1, 0] = math.nan
    after[2, n] = math.inf
    target = np.zeros((3, n))
    assert observer._saturated(before, after, target).tolist() == [False, True, True]

