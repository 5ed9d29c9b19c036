"""The independent-simulator suite: recordings from :mod:`.independent_sim` (its own integrator, PI
loop, Coulomb friction, actuation delay, 50 Hz, scrambled joints), in both control modes, with
commands stamped before, with and after their samples; ``identify`` on one nominal drive per
mode, then every fault type on every wheel and fault-free drives.
"""
import math
from pathlib import Path

import numpy as np

from youbot_fdi.bench.independent_sim import FAULTS, inverse, NAMES, simulate, STAMPINGS

MODES = ('velocity', 'effort')
CALIBRATION_SECONDS = 30.0
NOMINAL_SECONDS = 30.0
FAULT_SECONDS = 10.0
FAULT_AT = 5.0  # [s] into a fault drive
SEGMENT_RANGE = (0.6, 1.6)  # [s]
TWIST_LIMITS = (0.35, 0.3, 1.0)  # |v_x| [m/s], |v_y| [m/s], |w_z| [rad/s]
#: A wheel's command change that makes a runaway (the old command kept) visible [rad/s].
RUNAWAY_VISIBLE_CHANGE = 1.0


def drive(seed, seconds):
    """Random twists held for random times, ending at standstill: [(vx, vy, wz, seconds)]."""
    rng = np.random.default_rng(seed)
    segments, total = [], 0.0
    while total < seconds:
        length = float(min(rng.uniform(*SEGMENT_RANGE), seconds - total))
        segments.append((*(float(rng.uniform(-v, v)) for v in TWIST_LIMITS), length))
        total += length
    return segments + [(0.0, 0.0, 0.0, 0.5)]


def visible_at(segments, wheel, at):
    """When a runaway injected at ``at`` [s] first shows: the wheel's command changes enough."""
    ends = np.cumsum([s[3] for s in segments])
    held = None
    for k, end in enumerate(ends[:-1]):
        if end <= at:
            continue
        held = inverse(*segments[k][:3])[wheel] if held is None else held
        if abs(inverse(*segments[k + 1][:3])[wheel] - held) > RUNAWAY_VISIBLE_CHANGE:
            return float(end)
    return math.nan


def cases(seed=0):
    """(mode, name, fault, wheel index, stamping, seed) of every recording but the calibrations."""
    stampings = list(STAMPINGS)
    out = []
    for mode in MODES:
        for k, stamping in enumerate(stampings):
            out.append((mode, f'{mode}/nominal/{stamping}', None, None, stamping, seed + 10 + k))
        for f, fault in enumerate(FAULTS):
            for wheel in range(len(NAMES)) if fault != 'comm_loss' else (0,):
                stamping = stampings[(f + wheel) % len(stampings)]
                out.append((mode, f'{mode}/{fault}/{NAMES[wheel]}', fault, wheel, stamping,
                            seed + 100 + 10 * f + wheel))
    return out


def _calibrate(job):
    from youbot_fdi.bench.calibration import calibrate, residual_spread
    from youbot_fdi.model.profile import load_model
    mode, workdir, seed = job
    path = Path(workdir) / f'independent_calibration_{mode}'
    simulate(path, drive(seed, CALIBRATION_SECONDS), mode=mode, seed=seed)
    params, result = calibrate(path, load_model('youbot'), Path(workdir) / f'independent_params_{mode}')
    return params, result.coverage, residual_spread(result)


def _run(job):
    from youbot_fdi.bench.scoring import Case, replay_scored
    (mode, name, fault, wheel, stamping, seed), workdir, params = job
    segments = drive(seed, NOMINAL_SECONDS if fault is None else FAULT_SECONDS)
    path = Path(workdir) / name.replace('/', '_')
    at = FAULT_AT if fault else math.inf
    start = simulate(path, segments, fault=fault, wheel=wheel or 0, fault_time=at, seed=seed,
                     mode=mode, stamping=stamping)
    onset = at if fault != 'runaway' else visible_at(segments, wheel, at)
    duration = sum(s[3] for s in segments)
    case = Case(name, str(path), duration, fault,
                None if fault in (None, 'comm_loss') else NAMES[wheel],
                start + onset if fault else math.nan, fault, start, start + at if fault else math.nan)
    if fault and math.isnan(onset):
        return None  # a runaway whose command never changed is invisible
    return replay_scored(case, params)


def run_suite(workdir, progress=print, workers=2, seed=0):
    """Calibrate per mode, replay every case with the learned and the physics-only parameters;
    returns (summary line, {variant: result dicts}, residual spread by variant (velocity mode))."""
    from concurrent.futures import ProcessPoolExecutor
    from youbot_fdi.bench.calibration import VARIANTS
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    jobs = cases(seed)
    progress(f'independent simulator: identify per mode, then {len(jobs)} recordings ...')
    with ProcessPoolExecutor(workers) as pool:
        calibrated = dict(zip(MODES, pool.map(_calibrate, [(m, str(workdir), seed + 1) for m in MODES])))
        scored = [r for r in pool.map(_run, [(job, str(workdir), calibrated[job[0]][0]) for job in jobs])
                  if r is not None]
    summary = '; '.join(f'{mode}: bound coverage ' + ', '.join(f'{f} {c:.1%}' for f, c in cov.items())
                        for mode, (_, cov, _) in calibrated.items())
    return summary, {v: [r[v] for r in scored] for v in VARIANTS}, calibrated[MODES[0]][2]
