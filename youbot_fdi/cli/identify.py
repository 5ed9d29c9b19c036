"""``youbot-fdi identify``: model parameters and residual noise floors from a nominal recording."""
from pathlib import Path
import sys


from youbot_fdi.cli.status import DAMAGED

NAME = 'identify'


def _split_unknown(names, dynamics, deviation):
    """The wheels (of ``names``) whose identified Coulomb or viscous friction may be 0 within
    ``FRICTION_INTERVAL_SD`` of its standard deviation ``deviation`` ({parameter: sd}): the
    recording could not tell one from the other there."""
    from youbot_fdi.fdi.observer import FRICTION_INTERVAL_SD
    loose = []
    for w, name in enumerate(names):
        parts = (('coulomb_friction', dynamics.coulomb_friction[w]),
                 ('viscous_friction', dynamics.viscous_friction[w]))
        if any(f'{part}[{w}]' in deviation and level <= FRICTION_INTERVAL_SD * deviation[f'{part}[{w}]']
               for part, level in parts):
            loose.append(name)
    return loose


def _per_hour(rate):
    """An alarm rate [1/h] for people: 'one in N h', or 'never' at 0."""
    if rate <= 0.0:
        return 'never'
    return f'one in {1.0 / rate:.3g} h' if rate < 1.0 else f'{rate:.3g} per hour'

def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='identify model parameters from a nominal recording',
        description='Fit inertias, viscous and Coulomb friction (least squares with the profile as '
                    'a prior: each parameter printed with its standard deviation, the ones the '
                    'recording does not excite named and kept at the prior), the firmware PI '
                    'gains and input delay (velocity mode), whether the driver stops a wheel whose command is '
                    'older than command_timeout or holds its last command (no watchdog: the file says .inf), '
                    'run the report\'s friction sweep, report the fit (NRMSE '
                    'per wheel) and learn the residual noise floors the thresholds use. Writes a '
                    'parameter file for `replay --params`. A damaged recording (cut short) is used as '
                    'far as it can be read: exit status 3, with a line saying what was lost. Unless '
                    '--physics-only, also learns a correction of the physics where it holds out of '
                    'sample (friction by direction of travel, a per-wheel share of inertia; '
                    'youbot_fdi/fdi/learned.py); the bounds stay those of the physics residuals.')
    parser.add_argument('bag', help='rosbag2 directory of nominal (fault-free) driving')
    parser.add_argument('--output', required=True, help='parameter file to write (YAML)')
    parser.add_argument('--profile', default='youbot',
                        help='prior profile, youbot, robotino or a YAML file (default: youbot); its '
                             'values are the prior, their spread prior_inertia_sd and '
                             'prior_friction_sd in config/fdi.yaml')
    parser.add_argument('--no-gains', action='store_true', help='do not fit the firmware PI gains and input delay')
    parser.add_argument('--physics-only', action='store_true',
                        help='do not learn corrections of the physics (the direction-dependent '
                             'friction and the inertia the model misses); bounds from the physics '
                             'residuals alone')
    parser.add_argument('--roller-drag', action='store_true',
                        help='also fit the torque mecanum rollers pass to the motors while the base '
                             'moves sideways (roller_drag [N·m]; fit_roller_drag in config/fdi.yaml). '
                             'A closer fit, but tighter learned bounds: see docs/fdi.md before '
                             'using it on floors calibration did not cover')
    parser.add_argument('--plot', metavar='FILE', help='write the friction sweep (Fig. 5.10) here')
    parser.set_defaults(run=run)


def run(args):
    from dataclasses import replace

    import numpy as np

    from youbot_fdi.app.recordings import identify_recording
    from youbot_fdi.fdi.observer import FRICTION_INTERVAL_SD
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.model.profile import load_model, save_profile
    from youbot_fdi.settings import load_settings
    settings = load_settings(FdiSettings, 'fdi')
    if args.roller_drag:
        settings = replace(settings, fit_roller_drag=True)
    result = identify_recording(args.bag, load_model(args.profile), settings,
                                fit_gains=not args.no_gains, learn=not args.physics_only)
    profile = result.profile
    save_profile(profile, args.output)
    dyn = profile.dynamics
    if result.damage is not None:
        print(f'{args.bag}: {result.damage.describe()}', file=sys.stderr)
    print(f'{args.bag}: {result.info["samples"]} samples over {result.info["duration_s"]:.1f} s')
    sd = result.info.get('uncertainty', {})

    def value(name, number, digits='.3g'):
        """``number`` with its standard deviation (± 1 sd) where the fit states one."""
        return f'{number:{digits}}' + (f' ± {sd[name]:{digits}}' if name in sd else '')

    n = len(dyn.viscous_friction)
    print(f'  mass {value("mass", dyn.mass)} kg, J_z {value("yaw_inertia", dyn.yaw_inertia)} kg·m², '
          f'J_w {value("wheel_inertia", dyn.wheel_inertia[0])} kg·m²'
          f'  (torque fit R² {result.info["torque_fit_r_squared"]:.4f})')
    print('  viscous friction D [N·m·s/rad]: '
          + ', '.join(value(f'viscous_friction[{j}]', dyn.viscous_friction[j], '.4f') for j in range(n)))
    print('  Coulomb friction [N·m]: '
          + ', '.join(value(f'coulomb_friction[{j}]', dyn.coulomb_friction[j], '.4f') for j in range(n))
          + (f'; contact law, roller friction ratio {dyn.roller_friction_ratio:g}, calibrated down to a '
             f'rolling share of {result.fdi.get("contact_share_floor", 0.0):.2f}'
             if dyn.roller_friction_ratio > 0 else '; per wheel (no contact law)'))
    if 'roller_drag' in sd or dyn.roller_drag > 0:
        print(f'  rollers\' drag the motors feel [N·m]: {value("roller_drag", dyn.roller_drag, ".4f")}'
              + ('' if 'roller_drag' in sd else ' (the profile\'s, not fitted: fit_roller_drag)'))
    law, noise = result.info.get('uncertainty_law', {}), result.info.get('uncertainty_noise', {})
    by_form = [name for name in law if law[name] > noise.get(name, 0.0)]
    if by_form:
        print(f'  the ± of {", ".join(by_form)} is mostly the friction law\'s form: a wider Coulomb '
              'step or the rollers\' drag explains this recording as well and shares the friction '
              'differently')
    loose = _split_unknown(profile.platform.names, dyn, sd)
    if loose:
        low, high = result.fdi['calibrated_speed_range']
        print(f'  friction split loose on {", ".join(loose)}: its Coulomb or viscous part may be 0 '
              f'within {FRICTION_INTERVAL_SD:g} standard deviations (driven at {low:.3g}-{high:.3g} '
              'rad/s, the wheel speeds\' norm). The bounds allow for either split on other floors '
              'and speeds, and catch less there; slow driving in the calibration recording (where '
              'the Coulomb part dominates) pins it down')
    unexcited = result.info.get('unexcited')
    if unexcited:
        print(f'  not excited by this recording (the data narrow them to no less than '
              f'{settings.excitation_share:.0%} of their prior spread): {", ".join(unexcited)}; '
              'kept near the prior profile\'s values')
    if result.info.get('inertias_unseen'):
        print(f'  mass and inertias: {result.info["inertias_unseen"]}; their ± reaches the prior '
              'profile\'s values')
    if profile.dynamics.loop_inertias:
        mass, yaw, wheel = profile.dynamics.loop_inertias
        print(f'  the velocity loop (stepped at its own period) moves the prior\'s: mass {mass:.4g} kg, '
              f'J_z {yaw:.4g} kg·m², J_w {wheel:.4g} kg·m² (loop_inertias)')
    drag = result.info.get('loop_fit_roller_drag')
    print(f'  firmware PI: kp {profile.firmware.velocity_kp:.3g} A/(rad/s), '
          f'ki {profile.firmware.velocity_ki:.3g} A/rad'
          + ('' if drag is None else f' (fitted with the rollers\' drag, {drag:.3g} N·m, which the '
             'FDI\'s model leaves out unless fit_roller_drag)'))
    if 'input_delay' in result.fdi:
        print(f'  input delay (commands to wheels): {1000 * result.fdi["input_delay"]:.1f} ms')
    if result.info.get('command_watchdog'):
        print(f'  driver\'s command watchdog: {result.info["command_watchdog"]}')
    best_at = int(np.argmin(result.sweep[1]))
    best = result.sweep[0][best_at]
    edge = ' (at its edge)' if best_at in (0, len(result.sweep[0]) - 1) else ''
    print(f'  friction sweep (report Fig. 5.10): best D = {best:.4f} on the grid '
          f'{result.sweep[0][0]:.4f}..{result.sweep[0][-1]:.4f}{edge}')
    names = ', '.join(f'{v:.2%}' for v in result.nrmse_currents)
    print(f'  NRMSE per wheel, predicted from currents: {names}')
    if result.nrmse_commands is not None:
        print('  NRMSE per wheel, predicted from commands: '
              + ', '.join(f'{v:.2%}' for v in result.nrmse_commands))
    verdict = 'holds' if np.all(result.nrmse_currents < 0.01) else 'does not hold'
    print(f'  the report\'s "error below 1 %" {verdict} for this recording')
    learning = result.info.get('learning')
    if isinstance(learning, dict):
        for note in learning['notes']:
            print(f'  learning: {note}')
        spread = learning['residual_rms']
        if spread:
            print('  learned correction (friction by direction and speed, inertia share): '
                  'residual RMS physics -> learned: ' + ', '.join(f'{family} {spread["physics"][family]:.4g} -> '
                                          f'{spread["learned"][family]:.4g}'
                                          for family in spread['physics']))
        torque = (result.profile.learned or {}).get('torque') or {}
        if torque.get('speed_range') is not None:
            speeds, accelerations = (np.array(torque[key]) for key in ('speed_range', 'acceleration_range'))
            print(f'  it holds where this recording has been: wheel speeds {speeds[:, 0].min():.3g} to '
                  f'{speeds[:, 1].max():.3g} rad/s, accelerations {accelerations[:, 0].min():.3g} to '
                  f'{accelerations[:, 1].max():.3g} rad/s² (per wheel in the file; outside: physics '
                  'only and a WARN unseen_operating_point)')
    print('  bound floors: ' + ', '.join(f'{k} {v:.4g}' for k, v in result.fdi.items()
                                        if k.endswith('_sigma')))
    print(f'  bounds: the {settings.bound_quantile:.0%} quantile of |r| on the operating point, '
          f'x{settings.bound_margin:g}; nominal samples inside: '
          + ', '.join(f'{family} {share:.2%}' for family, share in result.coverage.items()))
    rates = result.info.get('false_alarm_rate')
    if rates:
        total = sum(r['per_hour'] for r in rates.values())
        print(f'  expected false alarms (an upper bound, on driving like this recording; target '
              f'{settings.false_alarm_target:g} per hour): '
              + ', '.join(f'{test} {_per_hour(r["per_hour"])} at threshold {r["threshold"]:.3g}'
                          for test, r in rates.items())
              + f'; all tests: {_per_hour(total)}')
    learned = replace(settings, sample_interval=result.fdi['sample_interval'],
                      silent_samples=result.fdi['silent_samples'])
    wheel = (f'a wheel\'s after {learned.silent_samples} samples without its reading, '
             f'{1000 * learned.wheel_timeout:.0f} ms after the first' if learned.silent_samples
             else 'a wheel\'s after as long without its reading')
    print(f'  sample interval {1000 * learned.sample_interval:.1f} ms (comm_loss after '
          f'{1000 * learned.data_timeout:.0f} ms without data; {wheel})')
    if args.plot:
        from youbot_fdi.app.report import plot_friction_sweep
        plot_friction_sweep(result.sweep, Path(args.plot))
        print(f'friction sweep figure: {args.plot}')
    print(f'parameters: {args.output}')
    return DAMAGED if result.damage is not None and result.damage.lost else 0
