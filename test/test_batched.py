"""The batched replay path equals the one-sample-at-a-time path the live nodes run.

Block decoding against rosbags, chunked reading against message-by-message reading, the batched
residual generator and decision maker against their per-sample updates, the vectorised recursions
against their loops.
"""
from dataclasses import replace
import math
import warnings

from hypothesis import given, settings, strategies as st

import numpy as np
import pytest

from youbot_fdi.bag import RecordingReader, RecordingWriter
from youbot_fdi.bag.cdr import JointStateLayout
from youbot_fdi.app.config import build_pipeline
from youbot_fdi.fdi.decision import DecisionMaker
from youbot_fdi.app.config import load_residual_data, residual_data_for
from youbot_fdi.fdi.pipeline import FdiPipeline
from youbot_fdi.fdi.observer import shared_ratio
from youbot_fdi.fdi.recursions import (NEVER, affine_recursion, bounded_cusum, clip_recursion, cusum,
                                      decaying_peak, last_true_value, nan_median, run_lengths,
                                      scalar_recursion)
from youbot_fdi.fdi.residuals import FAMILIES, ResidualGenerator
from youbot_fdi.samples import SampleMapper
from youbot_fdi.model import load_model
from youbot_fdi.model.scenario import load_script
from youbot_fdi.tmcm.recordings import record_drive

JOINT_STATE = 'sensor_msgs/msg/JointState'
SMALL_CHUNK = 37  # messages: many chunk boundaries, none aligned with anything


@pytest.fixture(scope='module')
def typestore():
    from rosbags.typesys import get_typestore, Stores
    return get_typestore(Stores.ROS2_JAZZY)


def joint_state(typestore, sec, nanosec, frame_id, names, position, velocity, effort):
    types = typestore.types
    header = types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec), frame_id=frame_id)
    return types[JOINT_STATE](header=header, name=list(names), position=np.array(position, dtype=float),
                              velocity=np.array(velocity, dtype=float), effort=np.array(effort, dtype=float))


floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
arrays = st.lists(floats, max_size=6)


@settings(max_examples=150, deadline=None)
@given(sec=st.integers(-2**31, 2**31 - 1), nanosec=st.integers(0, 999_999_999),
       frame_id=st.text(max_size=9), names=st.lists(st.text(max_size=7), max_size=5),
       position=arrays, velocity=arrays, effort=arrays)
def test_block_decoding_equals_rosbags(typestore, sec, nanosec, frame_id, names, position,
                                       velocity, effort):
    msg = joint_state(typestore, sec, nanosec, frame_id, names, position, velocity, effort)
    raw = bytes(typestore.serialize_cdr(msg, JOINT_STATE))
    layout = JointStateLayout.parse(raw)
    assert layout is not None and layout.matches(raw)
    assert layout.names == tuple(names) and layout.frame_id == frame_id
    stamps, decoded = layout.decode([raw, raw])
    assert stamps.tolist() == [sec + nanosec / 1e9] * 2
    for got, expected in zip(decoded, (position, velocity, effort)):
        np.testing.assert_array_equal(got, np.array([expected, expected], dtype=float).reshape(2, -1))


def test_a_layout_recognises_its_messages_only(typestore):
    def raw(names, position, frame_id=''):
        msg = joint_state(typestore, 5, 7, frame_id, names, position, [1.0, 2.0], [])
        return bytes(typestore.serialize_cdr(msg, JOINT_STATE))

    layout = JointStateLayout.parse(raw(['fl', 'fr'], [0.5, 0.25]))
    assert layout.matches(raw(['fl', 'fr'], [-3.0, 9.0]))
    assert not layout.matches(raw(['fl', 'rr'], [0.5, 0.25]))  # same length, other name
    assert not layout.matches(raw(['fl', 'fr'], [0.5]))  # other array length
    assert not layout.matches(raw(['fl', 'fr'], [0.5, 0.25], 'x'))
    big_endian = b'\x00\x00' + raw(['fl', 'fr'], [0.5, 0.25])[2:]
    assert JointStateLayout.parse(big_endian) is None  # left to rosbags
    assert JointStateLayout.parse(b'\x00\x01\x00\x00\x01') is None


@pytest.fixture(scope='module')
def model():
    return load_model('youbot')


def test_chunks_equal_reading_message_by_message(tmp_path, model, typestore):
    """Layout changes, bad messages and both command kinds, across chunk boundaries."""
    names = list(model.wheel_names)
    path = tmp_path / 'mixed'
    rng = np.random.default_rng(4)
    with RecordingWriter(path, names, storage='mcap') as writer:
        for k in range(300):
            stamp = 50 + 0.01 * k
            values = rng.normal(size=(3, 4))
            if k % 50 == 7:
                values[1, 2] = math.nan
            if k % 70 == 11:
                writer.joint_state(stamp, values[0][:3], values[1], values[2])  # short
                continue
            if 120 <= k < 160:
                writer.names = names[::-1]  # another layout for a while, other joint order
            elif 160 <= k < 170:
                writer.names = names + ['gripper']
            else:
                writer.names = names
            writer.joint_state(stamp, *values)
            if k % 3 == 0:
                writer.wheel_command(stamp, 'velocity' if k % 2 else 'effort', values[0])
            if k == 200:
                writer.joint_state(stamp + 0.001, values[0], [], values[2])  # no velocity
    with RecordingReader(path, names) as reader:
        chunked = list(reader.samples())
        counters = dict(reader.counters)
    mapper = SampleMapper(names)
    expected = []
    with RecordingReader(path, names) as reader:
        for connection, timestamp, raw in reader._reader.messages(connections=reader.connections):
            msg = typestore.deserialize_cdr(raw, JOINT_STATE)
            if connection.topic == '/joint_states':
                stamp = msg.header.stamp.sec + msg.header.stamp.nanosec / 1e9
                sample = mapper.joint_sample(stamp, msg.name, msg.position, msg.velocity, msg.effort)
            else:
                sample = mapper.command_sample(timestamp / 1e9, msg.name, msg.velocity, msg.effort)
            if sample is not None:
                expected.append(sample)
    assert counters == mapper.counters
    assert counters['skipped_nan'] > 0 and counters['skipped_short'] > 0
    assert counters['skipped_no_values'] == 1
    assert len(chunked) == len(expected) > 300
    for got, want in zip(chunked, expected):
        assert type(got) is type(want) and got.stamp == want.stamp
        for field in ('position', 'velocity', 'effort', 'kind', 'values'):
            if hasattr(want, field):
                np.testing.assert_array_equal(getattr(got, field), getattr(want, field))


@pytest.fixture(scope='module')
def recordings(tmp_path_factory, model):
    """A stuck wheel (the PI loop saturates), friction, a runaway, a freeze, a silent module,
    current mode, and faults raised early, latched, cleared and raised again on two wheels. The
    demo drive's segments as steps: a step saturates the PI loop the observer predicts."""
    script = load_script()[1].as_steps()
    root = tmp_path_factory.mktemp('batched')
    return {
        'stuck': record_drive(root / 'stuck', model, script, fault='stuck', wheel='wheel_joint_fr',
                              fault_time=4.0).path,
        'runaway': record_drive(root / 'runaway', model, script, fault='runaway',
                                wheel='wheel_joint_bl', fault_time=6.0).path,
        'freeze': record_drive(root / 'freeze', model, script, fault='encoder_freeze',
                               wheel='wheel_joint_fl', fault_time=5.0).path,
        'friction': record_drive(root / 'friction', model, script, fault='friction',
                                 wheel='wheel_joint_br', fault_time=3.0).path,
        'silent': record_drive(root / 'silent', model, script, fault='comm_loss',
                               wheel='wheel_joint_fr', fault_time=8.0).path,
        'effort': record_drive(root / 'effort', model, script, mode='effort', fault='torque_loss',
                               wheel='wheel_joint_br', fault_time=5.0).path,
        'relapse': record_drive(root / 'relapse', model, script, fault='encoder_freeze',
                                wheel='wheel_joint_fl', fault_time=0.5,
                                more_faults=[(None, None, 2.5), ('encoder_freeze', 'wheel_joint_fl', 6.0),
                                             (None, None, 7.5), ('stuck', 'wheel_joint_br', 9.0)]).path,
    }


def sample_by_sample(path, model, settings):
    """Residual frames and events the way the live nodes compute them: one message at a time."""
    generator = ResidualGenerator(model, settings)
    decision = DecisionMaker(model.wheel_names, settings, load_residual_data())
    frames, events = [], []
    with RecordingReader(path, model.wheel_names, keep_partial=True) as reader:
        for sample in reader.samples():
            if hasattr(sample, 'kind'):
                generator.command(sample)
                continue
            frame = generator.update(sample)
            if frame is not None:
                frames.append(frame)
                events += decision.update(frame)
    return frames, events


@pytest.fixture(scope='module')
def randomized_recordings(tmp_path_factory, model):
    """Two drives of plants from the randomized suite (not the FDI's model; their own rates,
    jitter, lost samples, sparse commands), each with a fault, at the default profile's
    parameters: alarms all along, so every decision path is exercised."""
    from youbot_fdi.bench import plant, randomized
    root = tmp_path_factory.mktemp('randomized')
    rng = np.random.default_rng(3)
    params = randomized.draw_plants(2, rng)
    drives = [randomized.judged_drive(rng, params.mass[p], 8.0, fault, p, magnitude)[0]
              for p, (fault, magnitude) in enumerate([('torque_loss', 0.3), ('encoder_freeze', 1.0)])]
    paths = []
    for p, recording in enumerate(plant.simulate(params, drives, seed=3)):
        paths.append(str(root / f'plant{p}'))
        randomized.write(recording, paths[-1], model.wheel_names)
    return paths


@pytest.mark.parametrize('size', [1, SMALL_CHUNK])
@pytest.mark.parametrize('plant', [0, 1])
def test_any_chunking_gives_the_same_events(randomized_recordings, model, plant, size):
    """Batch-size independence: a recording fed a message at a time, or in chunks that align
    with nothing, gives the events of feeding it whole (every stage keeps its state between
    batches; a batch of one is the live path's)."""
    def events(chunk):
        _, pipeline = build_pipeline()
        with RecordingReader(randomized_recordings[plant], model.wheel_names, keep_partial=True) as reader:
            return [e.to_dict() for part in reader.chunks(size=chunk) for e in pipeline.feed(part)]
    whole = events(10 ** 9)
    assert any(e['level'] == 'ERROR' for e in whole)
    assert events(size) == whole


@pytest.mark.parametrize('name, input_delay', [('stuck', 0.0), ('friction', 0.0), ('runaway', 0.0),
                                               ('runaway', 0.03), ('freeze', 0.0), ('silent', 0.0),
                                               ('effort', 0.02), ('relapse', 0.0)])
def test_batched_replay_equals_sample_by_sample(recordings, model, name, input_delay):
    _, pipeline = build_pipeline()
    settings = replace(pipeline.settings, input_delay=input_delay)
    if name == 'relapse':  # every raw change published as it comes: the latch itself is compared
        settings = replace(settings, heal_time=0.0, dwell=0.0)
    pipeline = FdiPipeline(model, settings, residual_data_for(model, settings), keep_frames=True)
    stepped = []
    original = pipeline.generator.observer._stepped
    pipeline.generator.observer._stepped = lambda *args: stepped.append(1) or original(*args)
    with RecordingReader(recordings[name], model.wheel_names, keep_partial=True) as reader:
        events = [e for chunk in reader.chunks(size=SMALL_CHUNK) for e in pipeline.feed(chunk)]
    frames, expected = sample_by_sample(recordings[name], model, pipeline.settings)
    assert [e.to_dict() for e in events] == [e.to_dict() for e in expected]
    assert any(e.level == 'ERROR' for e in events)
    if name == 'relapse':  # raised early, latched, cleared, raised again; then another wheel
        assert [(e.level, e.wheel) for e in events if e.wheel][:3] == [
            ('ERROR', 'wheel_joint_fl'), ('OK', 'wheel_joint_fl'), ('ERROR', 'wheel_joint_fl')]
        assert any(e.level == 'ERROR' and e.wheel == 'wheel_joint_br' for e in events)
    batch = pipeline.residuals()
    np.testing.assert_array_equal(batch.stamp, [f.stamp for f in frames])
    for family in FAMILIES:
        np.testing.assert_allclose(batch.values[family], [f.values[family] for f in frames],
                                   rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(batch.bounds[family], [f.bounds[family] for f in frames],
                                   rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(batch.frozen, [f.frozen for f in frames])
    np.testing.assert_array_equal(batch.effort_frozen, [f.effort_frozen for f in frames])
    if name == 'stuck':
        assert stepped, 'the saturating PI loop was never stepped period by period'


def test_batched_replay_equals_sample_by_sample_with_a_learned_correction(recordings, model):
    """The learned correction (issue 12) is evaluated alike one sample at a time and in blocks,
    with its calibrated range (some rows outside it) and the WARN it gives; the replay's pooled
    residual spread is the RMS of its residual frames."""
    from youbot_fdi.model.profile import PlatformModel
    learned = {'torque': {'weights': [[0.02, 0.01, 0.001, 0.0], [-0.01, 0.02, 0.0, 1e-4],
                                      [0.015, -0.01, 0.002, 0.0], [0.0, 0.01, -0.001, -1e-4]],
                          'limit': [0.05] * 4, 'inertia_limit': [0.02] * 4, 'speed_scale': 0.05,
                          'speed_range': [[-6.0, 6.0]] * 4, 'acceleration_range': [[-40.0, 40.0]] * 4}}
    corrected = PlatformModel(replace(model.profile, learned=learned))
    settings = build_pipeline()[1].settings
    pipeline = FdiPipeline(corrected, settings, residual_data_for(corrected, settings), keep_frames=True)
    assert pipeline.generator.correction is not None
    with RecordingReader(recordings['friction'], model.wheel_names) as reader:
        events = [e for chunk in reader.chunks(size=SMALL_CHUNK) for e in pipeline.feed(chunk)]
    frames, expected = sample_by_sample(recordings['friction'], corrected, settings)
    assert [e.to_dict() for e in events] == [e.to_dict() for e in expected]
    np.testing.assert_allclose(pipeline.residuals().values['torque'], [f.values['torque'] for f in frames],
                               rtol=1e-9, atol=1e-12)
    outside = pipeline.residuals().outside_calibration
    np.testing.assert_array_equal(outside, [f.outside_calibration for f in frames])
    assert 0 < np.count_nonzero(outside) < len(outside)
    assert any(e.fault == 'unseen_operating_point' for e in events)
    for family, rms in pipeline.spread.rms().items():
        values = pipeline.residuals().values[family]
        assert rms == pytest.approx(np.sqrt(np.mean(values[np.isfinite(values)] ** 2)), rel=1e-9)
    physics = FdiPipeline(model, settings, residual_data_for(model, settings), keep_frames=True)
    with RecordingReader(recordings['friction'], model.wheel_names) as reader:
        for chunk in reader.chunks():
            physics.feed(chunk)
    assert not np.allclose(physics.residuals().values['torque'], pipeline.residuals().values['torque'])


@pytest.mark.parametrize('gap', [100, 3 * SMALL_CHUNK])  # within a chunk, at a chunk's start
def test_gaps_and_repeated_stamps_restart_both_paths_alike(tmp_path, model, gap):
    """Missing and repeated samples: the generator restarts at the same rows either way."""
    _, pipeline = build_pipeline(keep_frames=True)
    path = tmp_path / 'jumpy'
    rng = np.random.default_rng(9)
    stamps = 20 + 0.01 * np.arange(400)
    stamps[gap:] += 0.5  # a gap: comm_loss of the base
    stamps[201] = stamps[200]  # a repeated stamp
    with RecordingWriter(path, model.wheel_names) as writer:
        for stamp in stamps:
            writer.joint_state(stamp, *rng.normal(scale=0.1, size=(3, 4)))
    with RecordingReader(path, model.wheel_names) as reader:
        events = [e for chunk in reader.chunks(size=SMALL_CHUNK) for e in pipeline.feed(chunk)]
    frames, _ = sample_by_sample(path, model, pipeline.settings)
    assert len(pipeline.residuals()) == len(frames) == len(stamps) - 3
    np.testing.assert_allclose(pipeline.residuals().values['torque'],
                               [f.values['torque'] for f in frames], rtol=1e-9, atol=1e-12)
    assert [(e.level, e.fault) for e in events if e.wheel is None] == [('ERROR', 'comm_loss'),
                                                                        ('OK', 'comm_loss')]


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(0, 40), size=st.integers(1, 5), seed=st.integers(0, 2**32 - 1))
def test_affine_recursion_equals_its_loop(rows, size, seed):
    rng = np.random.default_rng(seed)
    a = rng.normal(scale=0.6, size=(rows, size, size))
    a[rng.random(rows) < 0.2] = 0.0  # restarts
    b = rng.normal(size=(rows, size))
    x = x0 = rng.normal(size=size)
    expected = []
    for k in range(rows):
        x = a[k] @ x + b[k]
        expected.append(x)
    got = affine_recursion(a, b, x0)
    assert got.shape == (rows, size)
    np.testing.assert_allclose(got, np.reshape(expected, (rows, size)), rtol=1e-9, atol=1e-9)


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 70), seed=st.integers(0, 2**32 - 1))
def test_smoothing_and_cusums_equal_their_loops(rows, seed):
    """Exponential smoothing with a factor per row or per element, the CUSUM and the CUSUM held
    below a ceiling, from any state, equal their one-row loops."""
    rng = np.random.default_rng(seed)
    shape = (rows, 2, 3)
    factor_rows, factors = rng.random(rows), rng.random(shape)
    steps = rng.normal(scale=2.0, size=shape)
    start = rng.random(shape[1:]) * 6.0
    ceiling = rng.uniform(1.0, 8.0)
    flat = steps.reshape(rows, -1)
    by_row = by_element = plain = held = start.reshape(-1)  # each name is rebound, never changed
    expected = {name: [] for name in ('by_row', 'by_element', 'plain', 'held')}
    for k in range(rows):
        by_row = factor_rows[k] * by_row + flat[k]
        by_element = factors[k].reshape(-1) * by_element + flat[k]
        plain = np.maximum(0.0, plain + flat[k])
        held = np.clip(held + flat[k], 0.0, ceiling)
        for name, value in zip(expected, (by_row, by_element, plain, held)):
            expected[name].append(value)
    got = {'by_row': scalar_recursion(factor_rows, flat, start.reshape(-1)),
           'by_element': scalar_recursion(factors.reshape(rows, -1), flat, start.reshape(-1)),
           'plain': cusum(steps, start).reshape(rows, -1),
           'held': bounded_cusum(steps, start, ceiling).reshape(rows, -1)}
    for name, rows_expected in expected.items():
        np.testing.assert_allclose(got[name], rows_expected, rtol=1e-9, atol=1e-9, err_msg=name)


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 70), seed=st.integers(0, 2**32 - 1))
def test_a_clip_recursion_equals_its_loop(rows, seed):
    """``x_k = min(max(x_{k-1}, low_k), high_k)`` with rows that hold (-inf, inf), set (low =
    high) or clip, by its loop: the same bits (a clip does no arithmetic)."""
    rng = np.random.default_rng(seed)
    ends = np.sort(rng.normal(size=(rows, 2)), axis=1)
    kind = rng.integers(0, 3, rows)
    low = np.where(kind == 0, -np.inf, ends[:, 0])
    high = np.where(kind == 0, np.inf, np.where(kind == 1, ends[:, 0], ends[:, 1]))
    x = start = float(rng.normal())
    expected = []
    for k in range(rows):
        x = min(max(x, low[k]), high[k])
        expected.append(x)
    assert clip_recursion(low, high, start).tolist() == expected


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 40), wheels=st.integers(3, 5), seed=st.integers(0, 2**32 - 1))
def test_the_shared_ratio_is_the_same_in_any_chunking(rows, wheels, seed):
    """The ratio the wheels share (the load factor's and the rollers' drag's), rows with every
    number of voters, equals its row-by-row loop bit for bit."""
    rng = np.random.default_rng(seed)
    ratio = rng.uniform(0.2, 3.0, size=(rows, wheels))
    ratio[rng.random((rows, wheels)) < 0.45] = np.nan  # wheels that do not vote
    whole = shared_ratio(ratio, 1.0, 0.0)
    value, one_by_one = 1.0, []
    for k in range(rows):
        value = float(shared_ratio(ratio[k:k + 1], value, 0.0)[0])
        one_by_one.append(value)
    assert whole.tolist() == one_by_one


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 30), size=st.integers(1, 7), seed=st.integers(0, 2**32 - 1))
def test_a_decaying_peak_is_the_same_in_any_chunking(rows, size, seed):
    """``y_k = max(v_k, exp(-rate dt_k) y_{k-1})`` by its loop, and the same bits in chunks of any
    size (the state carried between them); NaN counts as nothing."""
    rng = np.random.default_rng(seed)
    values = np.where(rng.random((rows, 3)) < 0.4, 0.0, rng.exponential(size=(rows, 3)))
    values[rng.random((rows, 3)) < 0.1] = np.nan
    elapsed = np.cumsum(rng.uniform(0.001, 0.05, rows))[:, None]
    rate = np.array([0.0, 3.0, 40.0])  # [1/s]: never forgets, slowly, quickly
    peak, before, expected = np.zeros(3), 0.0, []
    for k in range(rows):
        peak = np.maximum(np.nan_to_num(values[k]), np.exp(-rate * (elapsed[k, 0] - before)) * peak)
        before = elapsed[k, 0]
        expected.append(peak)
    whole, _ = decaying_peak(values, elapsed, rate, np.full(3, -np.inf))
    np.testing.assert_allclose(whole, expected, rtol=1e-9, atol=1e-300)
    level, parts = np.full(3, -np.inf), []
    for start in range(0, rows, size):
        part, levels = decaying_peak(values[start:start + size], elapsed[start:start + size], rate, level)
        parts.append(part)
        level = levels[-1]
    np.testing.assert_array_equal(np.concatenate(parts), whole)


@settings(max_examples=80, deadline=None)
@given(rows=st.integers(0, 6), width=st.integers(1, 6), seed=st.integers(0, 2**32 - 1))
def test_nan_median_equals_numpys(rows, width, seed):
    """The rows' median without NaN, as numpy's nanmedian gives it (NaN for a row of NaN)."""
    rng = np.random.default_rng(seed)
    values = rng.normal(size=(rows, width))
    values[rng.random((rows, width)) < 0.3] = np.nan
    values[rng.random((rows, width)) < 0.2] = 1.0  # ties
    with np.errstate(all='ignore'), warnings.catch_warnings():
        warnings.simplefilter('ignore', RuntimeWarning)  # numpy warns of all-NaN rows
        expected = np.nanmedian(values, axis=-1)
    np.testing.assert_array_equal(nan_median(values), expected)
    np.testing.assert_array_equal(nan_median(values[0]) if rows else [], expected[0] if rows else [])


@settings(max_examples=80, deadline=None)
@given(flags=st.lists(st.lists(st.booleans(), min_size=3, max_size=3), max_size=30),
       carry=st.lists(st.integers(0, 9), min_size=3, max_size=3), seed=st.integers(0, 999))
def test_run_lengths_and_last_values_equal_their_loops(flags, carry, seed):
    rows = len(flags)
    flags = np.array(flags, dtype=bool).reshape(rows, 3)
    restart = np.random.default_rng(seed).random(rows) < 0.15
    count, expected = np.array(carry), []
    for k in range(rows):
        count = np.where(flags[k] & ~restart[k], count + 1, 0)
        expected.append(count)
    np.testing.assert_array_equal(run_lengths(flags, np.array(carry), restart),
                                  np.reshape(expected, (rows, 3)))
    values = np.arange(rows) * 10.0
    latest, expected = -1.0, []
    for k in range(rows):
        latest = values[k] if restart[k] else latest
        expected.append(latest)
    np.testing.assert_array_equal(last_true_value(restart, values, -1.0), expected)


@settings(max_examples=80, deadline=None)
@given(rows=st.integers(1, 60), seed=st.integers(0, 2**32 - 1))
def test_batched_alarms_equal_the_sequential_evidence_latch(model, rows, seed):
    """Evidence (the magnitude CUSUM, and the torque shift CUSUMs against a level that holds still
    while the wheel's torque alarm is set), the shared-evidence rule, alarms raised only by evidence
    that grows, and release hysteresis over a
    block, from any state it was left in, equal the one-row recursions; so do the rows in which the
    base breaks away from rest (no torque evidence, the level starts afresh) and those in which
    the wheels leave the level's operating point (the level starts afresh)."""
    from youbot_fdi.fdi.settings import FdiSettings
    settings_ = FdiSettings(release_time=0.05, shared_window=0.5, shift_time_constant=0.3)
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
    threshold = s.family_thresholds[0]  # the same for every family by default
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
    from youbot_fdi.fdi.settings import FdiSettings
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


def test_the_replay_benchmark_compares_with_decoding_in_the_same_run():
    """Every case of issue 14 is timed against decoding its own recording; the fault cases show
    their alarms on the faulty wheels (the cases are what they say)."""
    from youbot_fdi.bench.speed import bench_replay, REPLAY_WHEELS
    seconds = 12.0
    *cases, identified, command_line, live, learned = bench_replay(progress=lambda text: None,
                                                                   seconds=seconds)
    assert identified.name == 'identify: the 12 s fault-free recording'
    assert identified.baseline == cases[0].value and identified.value > 0  # against its replay
    # as a user runs them: a fresh interpreter each pays its start, so each takes longer
    assert command_line.baseline_name == 'youbot-fdi replay of it'
    assert command_line.value > identified.value and command_line.baseline > cases[0].value
    names = [c.name for c in cases]
    assert names == ['replay: fault-free', 'replay: fault-free, mcap', 'replay: a fault at 10 %',
                     'replay: faults on two wheels', 'replay: fault-free, no --params']
    for case in cases:
        assert case.baseline_name == 'rosbags decode-only' and 'messages' in case.note
    assert all(w in cases[3].note for w in REPLAY_WHEELS)
    assert REPLAY_WHEELS[0] in cases[2].note
    samples = seconds / 0.01  # the drive at the shim's 100 Hz
    assert live.baseline == pytest.approx(cases[0].value * 1e6 / samples, rel=0.05)  # µs per sample
    assert learned.value == live.value and learned.baseline_name == 'the same, physics only'
    for result in (*cases, identified, command_line, live, learned):
        assert result.value > 0 and result.baseline > 0 and math.isfinite(result.ratio)


def test_the_start_benchmark_times_a_fresh_interpreter():
    from youbot_fdi.bench.speed import bench_start
    result = bench_start()
    assert result.value > 0 and result.baseline > 0 and 'import numpy' in result.baseline_name
