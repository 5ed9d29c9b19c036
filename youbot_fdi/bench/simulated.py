"""The fault benchmark: every fault type on every wheel, in both control modes, on plants the FDI
was not built for.

Per plant variation (the first is the nominal youBot profile, the others are random): the true
plant's mass, inertias, per-wheel viscous friction, Coulomb friction (a friction law the prior
model does not have), firmware PI gains, measurement noise and measurement delay are drawn at
random. As a user would, the FDI is then calibrated with ``identify`` on one nominal recording of
that plant in each control mode (velocity commands, or open-loop efforts in current mode), and
replays, per mode,

- a long fault-free drive with aggressive transients and rotations (false alarms per hour), and
- one recording per fault type and wheel, the fault injected at a random moment.

Everything goes through the whole shim path (commands -> CAN process data -> virtual modules ->
/joint_states), so quantisation (ticks, rpm, mA) is in the data. Printed: detection rate,
isolation accuracy (wheel), type accuracy, median and p90 detection delay, false alarms per hour,
and replay time against merely decoding the recordings.
"""
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, replace
import math
from pathlib import Path
import tempfile
import time

import numpy as np

from youbot_fdi.faults import INJECTABLE
from youbot_fdi.model.profile import load_model, PlatformModel
from youbot_fdi.model.scenario import DriveScript, Segment

FAULT_DURATION = 16.0  # [s] per fault recording
NOMINAL_DURATION = 60.0  # [s] per fault-free recording
CALIBRATION_DURATION = 30.0  # [s] nominal recording for identify
SEGMENT_RANGE = (0.4, 1.8)  # [s]
TWIST_LIMITS = (0.45, 0.35, 1.4)  # |v_x| [m/s], |v_y| [m/s], |w_z| [rad/s]
PAUSE_PROBABILITY = 0.15
#: A change of a wheel's command that makes a runaway (the old drive kept) visible, per mode:
#: [rad/s] in velocity mode, [N·m] in current mode (about five effort noise floors).
RUNAWAY_VISIBLE_CHANGE = {'velocity': 1.0, 'effort': 0.1}
MODES = ('velocity', 'effort')
TIMING_REPEATS = 2  # replay and decode-only timed this many times each; the best counts


@dataclass(frozen=True)
class Variation:
    """A perturbed true plant and its measurement chain."""

    index: int
    mass_scale: float = 1.0
    yaw_scale: float = 1.0
    wheel_inertia_scale: float = 1.0
    friction_scales: tuple = (1.0, 1.0, 1.0, 1.0)
    coulomb: tuple = (0.0, 0.0, 0.0, 0.0)  # [N·m]
    gain_scale: float = 1.0
    current_noise: float = 5.0  # [mA]
    velocity_noise: float = 1.0  # [rpm]
    measurement_delay: float = 0.0  # [s]

    def describe(self):
        return (f'plant {self.index}: m x{self.mass_scale:.2f}, J_z x{self.yaw_scale:.2f}, '
                f'J_w x{self.wheel_inertia_scale:.2f}, D x{min(self.friction_scales):.2f}..'
                f'{max(self.friction_scales):.2f}, Coulomb {max(self.coulomb):.3f} N·m, '
                f'PI x{self.gain_scale:.2f}, noise {self.current_noise:.0f} mA / '
                f'{self.velocity_noise:.1f} rpm, delay {self.measurement_delay * 1000:.0f} ms')


def make_variations(count, seed=0):
    """The nominal plant, then ``count - 1`` random ones."""
    rng = np.random.default_rng(seed)
    variations = [Variation(0)]
    for index in range(1, count):
        variations.append(Variation(
            index, mass_scale=rng.uniform(0.8, 1.2), yaw_scale=rng.uniform(0.6, 1.4),
            wheel_inertia_scale=rng.uniform(0.8, 1.25),
            friction_scales=tuple(rng.uniform(0.7, 1.5, 4)), coulomb=tuple(rng.uniform(0.0, 0.06, 4)),
            gain_scale=rng.uniform(0.7, 1.4), current_noise=rng.uniform(2.0, 15.0),
            velocity_noise=rng.uniform(0.5, 3.0), measurement_delay=float(rng.choice([0.0, 0.002, 0.005]))))
    return variations


def true_model(prior, variation):
    """The plant a variation describes."""
    dyn = prior.dynamics.parameters
    dynamics = replace(dyn, mass=dyn.mass * variation.mass_scale,
                       yaw_inertia=dyn.yaw_inertia * variation.yaw_scale,
                       wheel_inertia=tuple(v * variation.wheel_inertia_scale for v in dyn.wheel_inertia),
                       viscous_friction=tuple(v * s for v, s in zip(dyn.viscous_friction,
                                                                    variation.friction_scales)),
                       coulomb_friction=tuple(variation.coulomb))
    firmware = replace(prior.firmware, velocity_kp=prior.firmware.velocity_kp * variation.gain_scale,
                       velocity_ki=prior.firmware.velocity_ki * variation.gain_scale)
    return PlatformModel(replace(prior.profile, dynamics=dynamics, firmware=firmware))


def random_script(seed, duration):
    """An aggressive drive: random twists held for random times, with pauses."""
    rng = np.random.default_rng(seed)
    segments, total = [], 0.0
    while total < duration:
        length = min(rng.uniform(*SEGMENT_RANGE), duration - total)
        if length <= 0:
            break
        twist = ((0.0, 0.0, 0.0) if rng.random() < PAUSE_PROBABILITY else
                 tuple(float(rng.uniform(-limit, limit)) for limit in TWIST_LIMITS))
        segments.append(Segment(f's{len(segments)}', twist, length))
        total += length
    return DriveScript(tuple(segments))


def _visible_time(model, script, wheel_index, injected_at, mode='velocity'):
    """When a runaway injected at ``injected_at`` first shows: the wheel's command (speed, or in
    current mode effort) changes by ``RUNAWAY_VISIBLE_CHANGE``."""
    from youbot_fdi.tmcm.recordings import effort_for
    kin = model.kinematics
    ends = np.cumsum([s.duration for s in script.segments])
    speeds = [kin.inverse(s.twist) for s in script.segments] + [np.zeros(kin.n_wheels)]
    commands = [(v if mode == 'velocity' else effort_for(model, v))[wheel_index] for v in speeds]
    current = None
    for k, end in enumerate(ends):
        if end <= injected_at:
            continue
        if current is None:
            current = commands[k]
        if abs(commands[k + 1] - current) > RUNAWAY_VISIBLE_CHANGE[mode]:
            return float(end)
    return math.nan


def _timed_replay(path, params):
    """Replay and decode-only times [s] of one recording: the best of ``TIMING_REPEATS`` runs
    each, so one-time costs (imports, rosbags' generated decoders) and noise do not count."""
    from youbot_fdi.bag.reader import RecordingReader
    from youbot_fdi.app.config import build_pipeline
    from youbot_fdi.app.replay import replay_recording
    replay_times, decode_times = [], []
    for _ in range(TIMING_REPEATS):
        model, pipeline = build_pipeline(params)
        started = time.perf_counter()
        replay_recording(pipeline, path)
        replay_times.append(time.perf_counter() - started)
        started = time.perf_counter()
        with RecordingReader(path, model.wheel_names) as reader:
            reader.decode_only()
        decode_times.append(time.perf_counter() - started)
    return min(replay_times), min(decode_times)


def _calibrate(variation, workdir, seed, mode):
    """Record a nominal drive of the plant in ``mode`` and identify it; returns ({variant:
    parameter file}, residual spread by variant)."""
    from youbot_fdi.bench.calibration import calibrate, residual_spread
    from youbot_fdi.tmcm.recordings import record_drive
    prior = load_model('youbot')
    plant = true_model(prior, variation)
    path = workdir / f'calibration_{variation.index}_{mode}'
    record_drive(path, plant, random_script(seed, CALIBRATION_DURATION), mode=mode, **_chain(variation))
    params, result = calibrate(path, prior, workdir / f'params_{variation.index}_{mode}')
    return params, residual_spread(result)


def _chain(variation):
    return {'current_noise': variation.current_noise, 'velocity_noise': variation.velocity_noise,
            'measurement_delay': variation.measurement_delay, 'seed': variation.index}


def _run_case(case):
    """One recording, replayed with each variant's parameters and scored by the suites' one rule
    (:func:`~youbot_fdi.bench.scoring.replay_scored`); returns {variant: result dict} (runs in a
    worker process)."""
    from youbot_fdi.bench.scoring import Case, replay_scored
    from youbot_fdi.tmcm.recordings import DEFAULT_START_STAMP, record_drive
    variation, mode, fault, wheel, seed, workdir, params = case
    prior = load_model('youbot')
    plant = true_model(prior, variation)
    rng = np.random.default_rng(seed)
    duration = NOMINAL_DURATION if fault is None else FAULT_DURATION
    script = random_script(seed, duration)
    path = Path(workdir) / f'v{variation.index}_{mode}_{fault or "nominal"}_{wheel or ""}_{seed}'
    injected_at = float(rng.uniform(0.35, 0.6) * duration) if fault else math.nan
    record_drive(path, plant, script, mode=mode, fault=fault, wheel=wheel, fault_time=injected_at,
                 **_chain(variation))
    visible = injected_at  # a runaway shows once its wheel's command changes
    if fault == 'runaway':
        visible = _visible_time(plant, script, plant.wheel_names.index(wheel), injected_at, mode)
    scored = replay_scored(Case(path.name, str(path), duration, fault, wheel,
                                onset=DEFAULT_START_STAMP + visible, expected=fault,
                                start=DEFAULT_START_STAMP,
                                injected=DEFAULT_START_STAMP + injected_at), params)
    suite = {'variation': variation.index, 'mode': mode, 'observable': not math.isnan(visible),
             'path': str(path)}
    return {variant: {**result, **suite, 'params': params[variant]}
            for variant, result in scored.items()}


def run_fault_benchmark(variations=3, seed=0, workers=2, progress=print, workdir=None, modes=MODES):
    """Run the benchmark; returns (variations, {variant: list of result dicts}, residual spread by
    variant of the nominal plant's first mode's calibration)."""
    from youbot_fdi.bench.calibration import VARIANTS
    plants = make_variations(variations, seed)
    with tempfile.TemporaryDirectory(prefix='youbot_fdi_bench_') as tmp:
        root = Path(workdir or tmp)
        root.mkdir(parents=True, exist_ok=True)
        wheels = load_model('youbot').wheel_names
        calibrations = [(v, mode) for v in plants for mode in modes]
        progress(f'calibrating {len(plants)} plants in {len(modes)} control modes with identify ...')
        with ProcessPoolExecutor(workers) as pool:
            calibrated = list(pool.map(_calibrate, [v for v, _ in calibrations], [root] * len(calibrations),
                                       [seed + 1000 + v.index for v, _ in calibrations],
                                       [mode for _, mode in calibrations]))
            cases = []
            for (v, mode), (p, _) in zip(calibrations, calibrated):
                cases.append((v, mode, None, None, seed + 10 * v.index, str(root), p))
                for k, fault in enumerate(INJECTABLE):
                    for j, wheel in enumerate(wheels):
                        cases.append((v, mode, fault.value, wheel, seed + 100 * v.index + 10 * k + j,
                                      str(root), p))
            scored = []
            for n, result in enumerate(pool.map(_run_case, cases), 1):
                scored.append(result)
                if n % 10 == 0 or n == len(cases):
                    progress(f'  {n}/{len(cases)} recordings')
        results = {variant: [r[variant] for r in scored] for variant in VARIANTS}
        # Timed one at a time, in this process: a parallel worker would disturb the timings.
        progress('timing replay against decode-only ...')
        for result in results[VARIANTS[0]]:
            result['replay_time'], result['decode_time'] = _timed_replay(result['path'],
                                                                        result['params'])
    return plants, results, calibrated[0][1]


def summarise(plants, results):
    """The printed benchmark summary."""
    from youbot_fdi.bench.scoring import delay_quantiles, rate_text
    faulty = [r for r in results if r['fault'] and r['observable']]
    all_median, all_p90 = delay_quantiles(faulty)
    hours = sum(r['fault_free_seconds'] for r in results) / 3600.0
    false_alarms = sum(r['false_alarms'] for r in results)
    replay = sum(r.get('replay_time', 0.0) for r in results)
    decode = sum(r.get('decode_time', 0.0) for r in results)
    lines = ['Fault benchmark (youbot-fdi bench --faults)'] + ['  ' + p.describe() for p in plants]
    lines += ['', f'{"fault":<16}{"mode":<10}{"cases":>6}{"detected":>10}{"isolated":>10}{"named":>8}'
                  f'{"median delay":>14}{"p90 delay":>11}']
    modes = [m for m in MODES if any(r['mode'] == m for r in results)]
    for fault in sorted({r['fault'] for r in faulty}):
        for mode in modes:
            rows = [r for r in faulty if r['fault'] == fault and r['mode'] == mode]
            median, p90 = delay_quantiles(rows)
            lines.append(f'{fault:<16}{mode:<10}{len(rows):>6}{sum(r["detected"] for r in rows):>10}'
                         f'{sum(r["isolated"] for r in rows):>10}{sum(r["named"] for r in rows):>8}'
                         f'{median * 1000:>12.0f}ms{p90 * 1000:>9.0f}ms')
    for mode in modes:
        rows = [r for r in results if r['mode'] == mode]
        seconds = sum(r['fault_free_seconds'] for r in rows)
        lines.append(f'{mode} mode: false alarms {sum(r["false_alarms"] for r in rows)} in '
                     f'{seconds:.0f} s fault-free')
    wrong = sorted({(r['fault'], r['named_as']) for r in faulty if r['detected'] and not r['named']},
                   key=str)
    lines += ['', f'detection rate      {sum(r["detected"] for r in faulty)}/{len(faulty)}',
              f'isolation accuracy  {sum(r["isolated"] for r in faulty)}/{len(faulty)} (wheel)',
              f'type accuracy       {sum(r["named"] for r in faulty)}/{len(faulty)}'
              + (f'  (misnamed: {wrong})' if wrong else ''),
              f'detection delay     median {all_median * 1000:.0f} ms, '
              f'p90 {all_p90 * 1000:.0f} ms' if not math.isnan(all_median) else 'no delays',
              f'false alarms        {false_alarms} in {hours * 3600:.0f} s fault-free'
              f'{rate_text(false_alarms, hours)}' if hours else '',
              f'replay speed        {replay:.2f} s replay vs {decode:.2f} s decode-only = '
              f'{replay / decode:.2f}x decode (target 1.5x)']
    unobservable = [r for r in results if r['fault'] and not r['observable']]
    if unobservable:
        lines.append(f'({len(unobservable)} runaway cases never became visible: the wheel\'s '
                     'command did not change after the injection)')
    return '\n'.join(lines)
