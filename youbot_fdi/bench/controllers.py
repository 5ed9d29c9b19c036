"""The firmware PI (velocity mode) against the host-side model-based controller (current mode).

Each run drives a script on the virtual base through the driver shim's core in lockstep
(:class:`~youbot_fdi.tmcm.lockstep.LockstepBase`: process data over a virtual CAN bus, the
firmware loop, the exact dynamics), the same way for both controllers: the firmware PI gets the
wheel-speed set-points every cycle; the model-based controller
(:class:`~youbot_fdi.model.control.ModelBasedController`) gets them with the last measured
speeds and commands wheel torques (currents). Faults are the virtual base's own injections, so
both controllers meet the same faulty wheel.

Figures per run: RMS body-velocity tracking error against the simulator's true velocity (the
whole drive, or from the fault to the end), peak and RMS motor current (measured, all wheels).
"""
from dataclasses import dataclass
import math

import numpy as np

from youbot_fdi.config_paths import config_dir
from youbot_fdi.errors import ModelError
from youbot_fdi.faults import FaultKind, INJECTABLE
from youbot_fdi.model.control import ModelBasedController, ModelBasedSettings
from youbot_fdi.model.firmware import LoopKind
from youbot_fdi.model.kinematics import tracking_rms
from youbot_fdi.settings import load_settings
from youbot_fdi.tmcm.lockstep import LockstepBase

FIRMWARE_PI, MODEL_BASED = 'firmware_pi', 'model_based'
CONTROLLERS = (FIRMWARE_PI, MODEL_BASED)
CONTROLLER_TITLES = {FIRMWARE_PI: 'firmware PI (velocity mode)',
                     MODEL_BASED: 'model-based (current mode)'}
CONTROL_CONFIG = 'control.yaml'
SETTINGS_NAME = 'model_based_controller'
DRIVES = ('demo.yaml', 'aggressive.yaml')
PROFILES = ('youbot', 'seed')
FAULTS = (None, *(k.value for k in INJECTABLE))  # None: the fault-free drive
FAULT_WHEEL = 'wheel_joint_fl'
FAULT_AT_FRACTION = 0.4  # the fault goes in this far into the drive
CYCLE = 0.01  # process-data cycle [s], as the driver shim's default 100 Hz
#: Faults the report's continuous velocity loop (the seed profile) does not see: it runs its
#: precomputed closed loop, without the delivered torque, the friction or the fed-back reading.
UNSEEN_BY_CONTINUOUS_LOOP = tuple(k.value for k in (FaultKind.TORQUE_LOSS, FaultKind.FRICTION,
                                                    FaultKind.STUCK, FaultKind.ENCODER_FREEZE))


def load_controller_settings(path=None):
    """:class:`ModelBasedSettings` from ``config/control.yaml`` (or ``path``)."""
    return load_settings(ModelBasedSettings, SETTINGS_NAME, path or config_dir() / CONTROL_CONFIG)


@dataclass(frozen=True)
class ControlRun:
    """One drive under one controller; arrays per cycle."""

    controller: str
    profile: str
    drive: str
    fault: object  # fault name or None
    time: np.ndarray  # (k,) [s]
    commanded: np.ndarray  # (k, 3) twist set-point (vx, vy, wz)
    true: np.ndarray  # (k, 3) the simulator's body velocity
    current: np.ndarray  # (k, n) measured motor current [A]
    fault_at: float = math.nan  # [s]; nan without a fault
    note: str = ''  # why a run could not be made (then the arrays are empty)

    @property
    def ran(self):
        return not self.note

    def _since(self):
        return self.time >= (0.0 if math.isnan(self.fault_at) else self.fault_at)

    def tracking_error(self):
        """RMS tracking error (linear [m/s], angular [rad/s]) over the drive, or from the fault."""
        since = self._since()
        return tracking_rms(self.commanded[since], self.true[since])

    def peak_current(self):
        """Largest measured motor current [A] of any wheel."""
        return float(np.max(np.abs(self.current)))

    def rms_current(self):
        """RMS measured motor current [A] over all wheels and the whole drive."""
        return float(np.sqrt(np.mean(self.current ** 2)))


def run_drive(model, script, controller, fault=None, wheel=FAULT_WHEEL, fault_at=None,
              settings=None, profile='', drive=''):
    """Drive ``script`` on the virtual base of ``model`` under ``controller`` (one of
    CONTROLLERS); ``fault`` (a fault name) goes in on ``wheel`` at ``fault_at`` [s] (default
    :data:`FAULT_AT_FRACTION` of the drive). Returns a :class:`ControlRun`; a run the model
    cannot simulate (the report's continuous loop mixing modes) comes back with a ``note``."""
    if controller not in CONTROLLERS:
        msg = f'unknown controller {controller!r}; choose one of {", ".join(CONTROLLERS)}'
        raise ValueError(msg)
    kinematics, drive_train = model.kinematics, model.drive
    steps = int(round(script.duration / CYCLE))
    times = np.arange(steps) * CYCLE
    twists = script.twists(times)
    onset = (FAULT_AT_FRACTION * script.duration if fault_at is None else fault_at) if fault else math.nan
    empty = dict(time=np.zeros(0), commanded=np.zeros((0, 3)), true=np.zeros((0, 3)),
                 current=np.zeros((0, kinematics.n_wheels)))
    if (controller == FIRMWARE_PI and fault in UNSEEN_BY_CONTINUOUS_LOOP
            and model.firmware.loop == LoopKind.CONTINUOUS):
        note = f"the report's continuous velocity loop does not model {fault}"
        return ControlRun(controller, profile, drive, fault, fault_at=onset, note=note, **empty)
    host = (ModelBasedController(model, CYCLE, settings or load_controller_settings())
            if controller == MODEL_BASED else None)
    measured = np.zeros(kinematics.n_wheels)
    true, current = np.zeros((steps, 3)), np.zeros((steps, kinematics.n_wheels))
    with LockstepBase(model, CYCLE) as rig:
        try:
            for k in range(steps):
                if fault and times[k] >= onset and not rig.base.faults:
                    rig.base.inject(fault, wheel)
                target = kinematics.inverse(twists[k])
                if host is None:
                    sample = rig.step('velocity', kinematics.to_driver(target))
                else:
                    sample = rig.step('effort', kinematics.to_driver(host.torque(target, measured)))
                if sample is not None:  # else no reply yet: hold the last reading
                    measured = kinematics.from_driver(sample.velocity)
                    current[k] = drive_train.torque_to_current(sample.effort)
                true[k] = kinematics.forward(kinematics.from_driver(rig.base.wheel_state()[1]))
        except ModelError as err:
            return ControlRun(controller, profile, drive, fault, fault_at=onset, note=str(err), **empty)
    return ControlRun(controller, profile, drive, fault, times, twists, true, current, onset)


def compare(profiles=PROFILES, drives=DRIVES, faults=FAULTS, progress=None, settings=None):
    """Every (profile, drive, fault, controller) run; a list of :class:`ControlRun`."""
    from youbot_fdi.model.profile import load_model
    from youbot_fdi.model.scenario import load_script
    runs = []
    total = len(profiles) * len(drives) * len(faults) * len(CONTROLLERS)
    for profile in profiles:
        model = load_model(profile)
        for drive in drives:
            _, script = load_script(config_dir() / drive)
            for fault in faults:
                for controller in CONTROLLERS:
                    runs.append(run_drive(model, script, controller, fault, settings=settings,
                                          profile=profile, drive=drive))
                    if progress:
                        progress(f'[{len(runs)}/{total}] {profile}, {drive}, '
                                 f'{fault or "no fault"}, {controller}')
    return runs


def format_table(runs):
    """The comparison as a Markdown table: one row per (profile, drive, fault), both controllers."""
    rows = {}
    for run in runs:
        rows.setdefault((run.profile, run.drive, run.fault), {})[run.controller] = run
    lines = ['| profile | drive | fault (on fl) | controller | tracking RMS linear [m/s] | angular '
             '[rad/s] | peak current [A] | RMS current [A] |',
             '|---|---|---|---|---|---|---|---|']
    for (profile, drive, fault), pair in rows.items():
        for controller in CONTROLLERS:
            run = pair.get(controller)
            if run is None:
                continue
            head = f'| {profile} | {drive.removesuffix(".yaml")} | {fault or "none"} | {controller} |'
            if not run.ran:
                lines.append(f'{head} not simulated: {run.note} | | | |')
                continue
            linear, angular = run.tracking_error()
            lines.append(f'{head} {linear:.4f} | {angular:.4f} | {run.peak_current():.2f} | '
                         f'{run.rms_current():.2f} |')
    return '\n'.join(lines)


def plot(runs, path):
    """The figure: per profile, the aggressive drive's forward and yaw velocity under both
    controllers (no fault), and the tracking error per fault. Returns the path, or None when
    matplotlib is missing."""
    try:
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    profiles = list(dict.fromkeys(r.profile for r in runs))
    drive = DRIVES[-1] if any(r.drive == DRIVES[-1] for r in runs) else runs[0].drive
    fig, axes = plt.subplots(len(profiles), 3, figsize=(15, 4 * len(profiles)), squeeze=False)
    for row, profile in zip(axes, profiles):
        nominal = [r for r in runs if r.profile == profile and r.drive == drive and r.fault is None
                   and r.ran]
        for axis, (column, label) in zip(row[:2], ((0, 'vx [m/s]'), (2, 'wz [rad/s]'))):
            if nominal:
                axis.plot(nominal[0].time, nominal[0].commanded[:, column], 'k--', lw=1,
                          label='commanded')
            for run in nominal:
                axis.plot(run.time, run.true[:, column], lw=1.2, label=CONTROLLER_TITLES[run.controller])
            axis.set_title(f'{profile}, {drive.removesuffix(".yaml")} drive, no fault')
            axis.set_xlabel('time [s]')
            axis.set_ylabel(label)
            axis.legend(fontsize=7)
        faulty = [r for r in runs if r.profile == profile and r.drive == drive and r.ran]
        faults = list(dict.fromkeys(r.fault for r in faulty))
        width = 0.8 / len(CONTROLLERS)
        for index, controller in enumerate(CONTROLLERS):
            values = [next((r.tracking_error()[0] for r in faulty
                            if r.fault == f and r.controller == controller), np.nan) for f in faults]
            row[2].bar(np.arange(len(faults)) + index * width, values, width,
                       label=CONTROLLER_TITLES[controller])
        row[2].set_xticks(np.arange(len(faults)) + width / 2, [f or 'none' for f in faults],
                          rotation=30, fontsize=8)
        row[2].set_yscale('log')
        row[2].set_ylabel('RMS linear tracking error [m/s]')
        row[2].set_title(f'{profile}: tracking error after a fault on fl (from the fault)')
        row[2].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
