"""The randomized fault suite (``youbot-fdi bench --faults --suites randomized``).

Hundreds of plants (:mod:`youbot_fdi.bench.plant`, written apart from the FDI's model code) drawn
from wide ranges: mass, inertias, viscous, Coulomb and direction-dependent friction, roller and
rolling resistance, traction, the true torque constant, firmware gains, current limits that
saturate, actuation delay 0-5 ms, velocity or current mode, 20-500 Hz sampling with up to
+-30 % jitter and 10 % of samples lost, commands with every sample or sparse (10-20 Hz, some only
on change), quantised or continuous encoders, speed readings differentiated from the encoder,
lagging or noisy.

Each plant is calibrated as a user would: ``identify`` on its own 60 s nominal drive, gentle and
at moderate speed, on one floor, without payload. It is then judged on drives wider than that:
aggressive and gentle, faster, with starts and stops, on floors x0.5 to x3, with payloads from
-40 % to +60 % of its mass, put on or taken off while it stands, and on faults injected mid-drive
at their default and a smaller magnitude. Nothing is tuned per plant or per suite.
"""
from dataclasses import dataclass
import math
from pathlib import Path

import numpy as np

from youbot_fdi.bench import plant

PLANTS = 200
CALIBRATION_SECONDS = 60.0
RUN_SECONDS = 60.0  # each fault-free judged drive [s]
FAULT_FREE_RUNS = 6  # per plant: 200 x 6 x 60 s = 20 h
FAULT_RUN_SECONDS = 20.0
FAULT_WINDOW = (8.0, 12.0)  # a fault begins in this stretch of its run [s]
#: (fault, magnitude, label): every contract fault at its default magnitude, two at a smaller one.
FAULTS = (('stuck', 1.0, 'stuck'), ('torque_loss', 0.3, 'torque_loss x0.3'),
          ('torque_loss', 0.6, 'torque_loss x0.6'), ('friction', 6.0, 'friction x6'),
          ('friction', 3.0, 'friction x3'), ('runaway', 1.0, 'runaway'),
          ('encoder_freeze', 1.0, 'encoder_freeze'), ('comm_loss', 1.0, 'comm_loss'))
#: Faults at their default magnitude (the issue's detection targets are about these).
DEFAULT_MAGNITUDE = ('stuck', 'torque_loss x0.3', 'friction x6', 'runaway', 'encoder_freeze',
                     'comm_loss')
RATES = (20.0, 25.0, 50.0, 100.0, 125.0, 200.0, 250.0, 500.0)  # [Hz]
MAX_WHEEL_SPEED = 12.0  # [rad/s] no drive asks a wheel for more
START_STAMP = 1_760_000_000.0  # [s]
PROFILE = 'youbot'
#: Identification against truth: a stated value ± this many standard deviations should hold the
#: truth in 95 % of plants if the deviations are honest.
INTERVAL_SDS = 2.0


# ---------------------------------------------------------------------- plants and drives
def draw_plants(count, rng):
    """``count`` plants from the suite's ranges (:class:`~youbot_fdi.bench.plant.PlantParameters`)."""
    def uniform(low, high, shape=None):
        return rng.uniform(low, high, count if shape is None else (count, shape))

    def each_wheel(base, low, high):
        return base[:, None] * uniform(low, high, plant.WHEELS)

    mass = 23.6 * uniform(0.8, 1.25)
    sparse = rng.random(count) < 0.5
    return plant.PlantParameters(
        mass=mass, yaw_inertia=mass * (0.58 ** 2 + 0.38 ** 2) / 12.0 * uniform(0.7, 1.4),
        wheel_inertia=0.0095 * uniform(0.6, 1.5),
        viscous=each_wheel(0.035 * uniform(0.3, 2.0), 0.8, 1.25),
        coulomb=each_wheel(uniform(0.0, 0.08), 0.7, 1.3),
        asymmetry=uniform(-0.3, 0.3, plant.WHEELS),
        traction=uniform(0.4, 0.9), roller_resistance=uniform(0.005, 0.03),
        rolling_resistance=uniform(0.0002, 0.001), torque_scale=uniform(0.9, 1.1),
        kp=0.88 * np.exp(uniform(math.log(0.5), math.log(2.0))),
        ki=8.8 * np.exp(uniform(math.log(0.3), math.log(2.0))),
        current_limit=uniform(1.5, 3.564), current_lag=uniform(0.0002, 0.002),
        delay=uniform(0.0, 0.005), current_mode=rng.random(count) < 0.25,
        sample_rate=rng.choice(RATES, count),
        jitter=np.where(rng.random(count) < 0.5, uniform(0.0, 0.3), 0.02),
        drop=np.where(rng.random(count) < 0.3, 0.1, 0.0),
        command_rate=np.where(sparse, uniform(10.0, 20.0), 0.0),
        on_change=sparse & (rng.random(count) < 0.3),
        quantised=rng.random(count) < 0.7, speed_reading=rng.integers(0, 3, count),
        speed_lag=uniform(0.005, 0.04), speed_noise=uniform(0.005, 0.05),
        current_noise=uniform(0.002, 0.02))


def random_knots(rng, duration, top_speed, top_turn, acceleration, turn_acceleration,
                 stop_share=0.25):
    """Knots (times [s], twists (m, 3)) of a drive of random segments (1-4 s; a stop now and
    then), ramped at the given limits [m/s², rad/s²] (inf: steps), within MAX_WHEEL_SPEED."""
    times, twists = [0.0], [np.zeros(3)]
    t, current = 0.0, np.zeros(3)
    while t < duration - 1.0:
        hold = rng.uniform(1.0, 4.0)
        if rng.random() < stop_share:
            goal = np.zeros(3)
        else:
            heading = rng.uniform(-math.pi, math.pi)
            goal = np.array([math.cos(heading), math.sin(heading), 0.0]) * rng.uniform(0.2, 1.0) * top_speed
            goal[2] = rng.uniform(-1.0, 1.0) * top_turn * (rng.random() < 0.6)
            fastest = np.abs(plant.inverse_kinematics(goal)).max()
            if fastest > MAX_WHEEL_SPEED:
                goal *= MAX_WHEEL_SPEED / fastest
        change = goal - current
        ramp = max(np.hypot(*change[:2]) / acceleration, abs(change[2]) / turn_acceleration)
        ramp = min(ramp, hold)
        if ramp > 0.0:
            times.append(t + ramp)
            twists.append(goal.copy())
        t += hold
        times.append(min(t, duration))
        twists.append(goal.copy())
        current = goal
    times += [times[-1] + 0.5, duration + 1.0]
    twists += [np.zeros(3), np.zeros(3)]
    order = np.maximum.accumulate(np.array(times))
    return order, np.array(twists)


def calibration_drive(rng):
    """The user's nominal drive: gentle, moderate speeds, one floor, no payload."""
    knots, twists = random_knots(rng, CALIBRATION_SECONDS, 0.25, 0.6, 0.5, 1.0, stop_share=0.15)
    return plant.Drive(knots, twists, CALIBRATION_SECONDS)


def judged_drive(rng, mass, duration=RUN_SECONDS, fault=None, wheel=0, magnitude=1.0):
    """A drive wider than calibration: faster, aggressive or gentle, starts and stops, another
    floor (maybe changing), a payload (maybe put on or off while standing); a fault if given."""
    aggressive = bool(rng.random() < 0.5)
    acceleration, turn = (rng.uniform(2.0, 6.0), rng.uniform(3.0, 8.0)) if aggressive else (0.6, 1.2)
    knots, twists = random_knots(rng, duration, 0.45, 1.2, acceleration, turn)
    floor = float(np.exp(rng.uniform(math.log(0.5), math.log(3.0)))) if rng.random() < 0.6 else 1.0
    floor_after, floor_time = floor, math.inf
    if rng.random() < 0.4:
        floor_after = float(np.exp(rng.uniform(math.log(0.5), math.log(3.0))))
        floor_time = float(rng.uniform(0.3, 0.8) * duration)
    payload = float(rng.uniform(-0.4, 0.6) * mass) if rng.random() < 0.5 else 0.0
    payload_after, payload_time = payload, math.inf
    if rng.random() < 0.4:  # put on or taken off while the base stands
        resting = _rest_times(knots, twists, duration)
        if len(resting):
            payload_after = float(rng.uniform(-0.4, 0.6) * mass)
            payload_time = float(rng.choice(resting))
    offset = tuple(rng.uniform(-0.1, 0.1, 2))
    fault_time = float(rng.uniform(*FAULT_WINDOW)) if fault else math.inf
    drive = plant.Drive(knots, twists, duration, floor, floor_after, floor_time, payload,
                        payload_after, payload_time, offset, fault, wheel, fault_time, magnitude)
    return drive, (('aggressive', aggressive), ('acceleration', round(float(acceleration), 2)))


def conditions_of(drive):
    """(name, value) pairs of a drive's floor and payload (for tracing alarms)."""
    return (('floor', round(drive.floor, 2)), ('floor_after', round(drive.floor_after, 2)),
            ('floor_time', round(drive.floor_time, 2)), ('payload', round(drive.payload, 1)),
            ('payload_after', round(drive.payload_after, 1)),
            ('payload_time', round(drive.payload_time, 2)))


def _rest_times(knots, twists, duration):
    """Middles of the stretches in which the base is commanded to stand [s]."""
    still = np.all(np.abs(twists) < 1e-9, axis=1)
    middles = [0.5 * (knots[k] + knots[k + 1]) for k in range(len(knots) - 1)
               if still[k] and still[k + 1] and knots[k + 1] - knots[k] > 0.5 and knots[k + 1] < duration]
    return np.array(middles)


# ---------------------------------------------------------------------- the runs
@dataclass(frozen=True)
class Run:
    """One recording of the suite: which plant, what it is for, what was injected."""

    plant: int
    kind: str  # 'calibration', 'fault_free' or 'fault'
    label: str  # the fault's label (FAULTS), or ''
    path: str
    duration: float  # [s]
    fault: object = None
    wheel: object = None  # joint name
    onset: float = math.nan  # header stamp from which the fault can be seen [s]
    start: float = START_STAMP
    injected: float = math.nan  # header stamp of the injection (a runaway shows later) [s]
    conditions: tuple = ()  # (name, value) of the drive: floor, payload, style (to trace alarms)


def write(recording, path, names, storage='sqlite3'):
    """A plant's :class:`~youbot_fdi.bench.plant.Recording` as a rosbag2 recording; the start
    stamp [s]."""
    from youbot_fdi.bag.writer import RecordingWriter
    kind = 'effort' if recording.current_mode else 'velocity'
    commands = iter(zip(recording.command_stamp, recording.command))
    pending = next(commands, None)
    with RecordingWriter(path, names, storage) as writer:
        for k, stamp in enumerate(recording.stamp):
            while pending is not None and pending[0] <= stamp:
                writer.wheel_command(START_STAMP + pending[0], kind, pending[1])
                pending = next(commands, None)
            writer.joint_state(START_STAMP + stamp, recording.position[k], recording.velocity[k],
                               recording.effort[k])
    return START_STAMP


def _write(job):
    from youbot_fdi.model.profile import load_model
    recording, path = job
    write(recording, path, load_model(PROFILE).wheel_names)
    return path


def _calibrate(job):
    """``identify`` on plant ``index``'s nominal drive: (index, parameter files, what it found:
    {parameter: (value, standard deviation; NaN: none stated)} and the names it called not
    excited). A drive in velocity mode also fits the firmware's PI gains, which ``identify``
    states no deviation for."""
    from youbot_fdi.bench.calibration import calibrate
    from youbot_fdi.model.profile import load_model
    index, path, directory, velocity_mode = job
    params, result = calibrate(path, load_model(PROFILE), Path(directory) / f'params{index:03d}')
    dynamics, sd = result.profile.dynamics, result.info.get('uncertainty', {})
    values = {'mass': dynamics.mass, 'yaw_inertia': dynamics.yaw_inertia,
              'wheel_inertia': dynamics.wheel_inertia[0],
              **{f'viscous_friction[{j}]': v for j, v in enumerate(dynamics.viscous_friction)},
              **{f'coulomb_friction[{j}]': v for j, v in enumerate(dynamics.coulomb_friction)}}
    if velocity_mode:
        firmware = result.profile.firmware
        values.update(velocity_kp=firmware.velocity_kp, velocity_ki=firmware.velocity_ki)
    found = {name: (float(value), float(sd.get(name, math.nan))) for name, value in values.items()}
    return index, params, {'found': found, 'unexcited': list(result.info.get('unexcited', []))}


def truth_of(params, index):
    """Plant ``index``'s values in the FDI's terms: {parameter: value}. The FDI reads torque as
    current x the datasheet's constant, which is the true torque over ``torque_scale``, so every
    parameter it fits from torque is the plant's over that scale. The plant's wheel inertia
    includes the rotor's; its bearing friction is the FDI's viscous friction. The FDI's Coulomb
    friction is what holds a wheel back whatever its speed, by the sign of its own speed: the
    bearing's Coulomb friction (its direction asymmetry averages out over a drive) and the
    wheel's rolling resistance at the wheel's share of the weight (calibration drives carry no
    payload on the suite's own floor). The rollers' drag, which follows the base's motion and not
    the wheel's, is no per-wheel term: where it matters the stated deviation's model-form part
    (identify's rollers' drag alternative) says so. The firmware's PI gains act on the current
    the FDI reads, so they are the plant's as they are."""
    scale = float(params.torque_scale[index])
    rolling = float(params.rolling_resistance[index]) * plant.GRAVITY * float(params.mass[index]) / plant.WHEELS
    return {'mass': float(params.mass[index]) / scale,
            'yaw_inertia': float(params.yaw_inertia[index]) / scale,
            'wheel_inertia': float(params.wheel_inertia[index]) / scale,
            **{f'viscous_friction[{j}]': float(v) / scale for j, v in enumerate(params.viscous[index])},
            **{f'coulomb_friction[{j}]': (float(c) + rolling) / scale
               for j, c in enumerate(params.coulomb[index])},
            'velocity_kp': float(params.kp[index]), 'velocity_ki': float(params.ki[index])}


def identification_table(params, identified):
    """Identification against the plants' truth (issue 34): per parameter, the median and 90th
    percentile of |error| [%], the share of plants whose truth lies inside the stated
    value ± 2 standard deviations (a 95 % interval if the deviations are honest; "-" where none
    is stated), and the plants that named it not excited."""
    rows = {}
    for index, result in identified.items():
        truth = truth_of(params, index)
        for name, (value, sd) in result['found'].items():
            family = name.split('[')[0]
            error = (value - truth[name]) / truth[name]
            inside = None if math.isnan(sd) else abs(value - truth[name]) <= INTERVAL_SDS * sd
            excited = name not in result['unexcited']
            rows.setdefault(family, []).append((abs(error), inside, excited))
    lines = [f'Identification against truth ({len(identified)} plants, each from its own nominal '
             f'drive; Coulomb friction: the bearing\'s and the rolling resistance)',
             f'  {"parameter":<18}{"median |err|":>13}{"p90 |err|":>11}{"inside ±2 sd":>14}'
             f'{"not excited":>13}']
    for family, values in rows.items():
        error = np.array([v[0] for v in values])
        stated = [v[1] for v in values if v[1] is not None]
        inside = f'{np.mean(stated):.0%}' if stated else '-'
        lines.append(f'  {family:<18}{100 * np.median(error):>12.1f}%{100 * np.percentile(error, 90):>10.1f}%'
                     f'{inside:>14}{sum(not v[2] for v in values):>9}/{len(values)}')
    return '\n'.join(lines)


def _replay(job):
    from youbot_fdi.bench.scoring import Case, replay_scored
    run, params = job
    case = Case(f'plant{run.plant:03d}/{run.label or run.kind}', run.path, run.duration, run.label or None,
                run.wheel, run.onset, run.fault, run.start, run.injected)
    scored = replay_scored(case, {'learned': params['learned']})['learned']
    return run, {**scored, 'fault': run.label or None, 'spread': None}


def run_suite(workdir, progress=print, workers=2, seed=0, plants=PLANTS,
              fault_free_runs=FAULT_FREE_RUNS):
    """Draw, simulate, calibrate and replay the suite; returns (plant parameters, [(Run, result
    dict)], {plant: what identify found (:func:`_calibrate`)})."""
    from concurrent.futures import ProcessPoolExecutor
    from youbot_fdi.model.profile import load_model
    rng = np.random.default_rng(seed)
    workdir = Path(workdir) / 'randomized'
    workdir.mkdir(parents=True, exist_ok=True)
    names = load_model(PROFILE).wheel_names
    params = draw_plants(plants, rng)
    runs = []
    slots = [('calibration', None)] + [('fault_free', None)] * fault_free_runs + [('fault', f) for f in FAULTS]
    with ProcessPoolExecutor(workers) as pool:
        for slot, (kind, fault) in enumerate(slots):
            progress(f'randomized: simulating {kind} {fault[2] if fault else ""} drives of {plants} '
                     f'plants ({slot + 1}/{len(slots)}) ...')
            wheels = rng.integers(0, plant.WHEELS, plants)
            if kind == 'calibration':
                drives, styles = [calibration_drive(rng) for _ in range(plants)], [()] * plants
            elif kind == 'fault_free':
                drives, styles = zip(*[judged_drive(rng, params.mass[p]) for p in range(plants)])
            else:
                drives, styles = zip(*[judged_drive(rng, params.mass[p], FAULT_RUN_SECONDS, fault[0],
                                                    int(wheels[p]), fault[1]) for p in range(plants)])
            recordings = plant.simulate(params, drives, seed=seed * 1000 + slot)
            paths = [str(workdir / f'plant{p:03d}_{slot}') for p in range(plants)]
            list(pool.map(_write, zip(recordings, paths), chunksize=4))
            for p, (drive, recording) in enumerate(zip(drives, recordings)):
                runs.append(Run(p, kind, fault[2] if fault else '', paths[p], drive.duration,
                                fault[0] if fault else None, names[drive.wheel] if fault else None,
                                START_STAMP + recording.fault_visible if fault else math.nan,
                                injected=START_STAMP + drive.fault_time if fault else math.nan,
                                conditions=tuple(styles[p]) + conditions_of(drive)))
        calibration = [r for r in runs if r.kind == 'calibration']
        progress(f'randomized: identify on each plant\'s nominal drive ({plants}) ...')
        calibrated = list(pool.map(_calibrate, [(r.plant, r.path, str(workdir),
                                                 not params.current_mode[r.plant]) for r in calibration]))
        identified = {index: files for index, files, _ in calibrated}
        judged = [r for r in runs if r.kind != 'calibration']
        progress(f'randomized: {len(judged)} replays ...')
        scored = list(pool.map(_replay, [(r, identified[r.plant]) for r in judged], chunksize=8))
    return params, scored, {index: found for index, _, found in calibrated}


# ---------------------------------------------------------------------- the printed report
def summarise(params, scored):
    """The suite's report: hours, runs and hours with an alarm; detection per fault and magnitude."""
    from youbot_fdi.bench.scoring import summarise as suite_table
    results = [r for _, r in scored]
    fault_free = [(run, r) for run, r in scored if run.kind == 'fault_free']
    hours = sum(r['fault_free_seconds'] for r in results) / 3600.0
    alarmed = [(run, r) for run, r in scored if r['false_alarms']]
    alarmed_hours = sum(run.duration for run, _ in alarmed) / 3600.0
    lines = [f'Randomized suite: {len(params)} plants (plant.py, not the FDI\'s model), each calibrated '
             f'on its own {CALIBRATION_SECONDS:g} s gentle drive',
             f'  driven fault-free: {hours:.1f} h ({len(fault_free)} fault-free runs of '
             f'{RUN_SECONDS:g} s and the fault runs up to their fault); runs with an alarm: '
             f'{len(alarmed)} ({alarmed_hours:.2f} h of driving); false alarms: '
             f'{sum(r["false_alarms"] for r in results)} (ERROR events, with the types refined '
             f'within them: {sum(r["false_alarm_events"] for r in results)})']
    if alarmed:
        lines.append('  ' + describe_alarms(params, alarmed))
    lines.append('')
    # A fault whose wheel is never driven after it cannot be seen: not a detection case.
    unseen = {id(r) for run, r in scored if run.kind == 'fault' and math.isnan(run.onset)}
    visible = [r for r in results if id(r) not in unseen]
    lines.append(suite_table('Randomized suite, per fault and magnitude', visible))
    if unseen:
        lines.append(f'  ({len(unseen)} fault runs left out of detection: their wheel was not driven '
                     'after the fault, so it never showed)')
    default = [(run, r) for run, r in scored if id(r) not in unseen and r['fault'] in DEFAULT_MAGNITUDE]
    lines.append(f'  default magnitude: {_detection(r for _, r in default)}')
    modes = {mode: [r for run, r in default if bool(params.current_mode[run.plant]) == current]
             for mode, current in (('velocity', False), ('current', True))}
    lines.append('    by control mode: ' + '; '.join(f'{mode} mode {_detection(cases)}'
                                                     for mode, cases in modes.items() if cases))
    return '\n'.join(lines)


def _detection(results):
    """'found/cases detected and isolated; median .. ms, p90 .. ms' of fault results."""
    from youbot_fdi.bench.scoring import delay_quantiles
    results = list(results)
    found = sum(r['detected'] and r['isolated'] for r in results)
    median, p90 = delay_quantiles(results)
    return (f'{found}/{len(results)} detected and isolated; median {1000 * median:.0f} ms, '
            f'p90 {1000 * p90:.0f} ms')


def describe_alarms(params, alarmed):
    """Where the false alarms were: the alarm kinds and the plants' modes, rates and readings."""
    kinds = {}
    for _, r in alarmed:
        for fault in r['false_alarm_faults']:
            kinds[fault.split(':')[1]] = kinds.get(fault.split(':')[1], 0) + 1
    modes = {'current' if params.current_mode[run.plant] else 'velocity' for run, _ in alarmed}
    rates = sorted({int(params.sample_rate[run.plant]) for run, _ in alarmed})
    return (f'alarm kinds {kinds}; modes {sorted(modes)}; sample rates {rates} Hz; plants '
            f'{sorted({run.plant for run, _ in alarmed})[:20]}')
