"""``youbot-fdi simulate``: the model core alone on a scripted drive, with a summary and a figure.

The scripted base twists go through the inverse kinematics to wheel-speed commands (driver
convention, as ``/wheel_commands`` carries them), the firmware's velocity loop drives the exactly
discretised dynamics, and odometry integrates the resulting wheel angles. No ROS, no CAN.
"""
from pathlib import Path
import time

NAME = 'simulate'
DEFAULT_OUTPUT_DIR = 'out/simulate'
FIGURE_NAME = 'drive.png'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='simulate a scripted drive on the model alone (no ROS) and summarise it',
        description='Simulate a scripted drive (config/demo.yaml) on the youBot model: inverse '
                    'kinematics, firmware velocity loop, exact dynamics and odometry. Prints a '
                    'summary and writes a figure. Ends by itself.')
    parser.add_argument('--duration', type=float, default=None,
                        help='stretch or shrink the script to this many seconds (default: as '
                             'scripted, 12 s)')
    parser.add_argument('--profile', default=None,
                        help='parameter profile name or YAML path (default: from the script)')
    parser.add_argument('--script', default=None,
                        help='drive script YAML (default: config/demo.yaml)')
    parser.add_argument('--output-dir', default=DEFAULT_OUTPUT_DIR,
                        help=f'where the figure goes (default: {DEFAULT_OUTPUT_DIR})')
    parser.add_argument('--no-plot', action='store_true', help='do not write the figure')
    parser.set_defaults(run=run)


def simulate_drive(model, script):
    """Run ``script`` on ``model`` in velocity mode; returns a dict of time series (driver convention).

    Keys: ``time`` (k,), ``twist_cmd`` (k, 3), ``wheel_cmd``, ``wheel_speed``, ``current`` (k, n),
    ``pose_cmd``, ``pose_odom`` (k, 3).
    """
    import numpy as np

    from youbot_fdi.model.firmware import ControlMode
    from youbot_fdi.model.kinematics import integrate_pose, Odometry
    from youbot_fdi.model.simulation import BaseSimulator
    simulator = BaseSimulator(model)
    dt = simulator.step_size
    times = np.arange(1, int(round(script.duration / dt)) + 1) * dt
    twists = script.twists(times - dt)  # the command applied during each step
    kin = model.kinematics
    wheel_cmd = kin.to_driver(kin.inverse(twists))
    result = simulator.run(kin.from_driver(wheel_cmd), ControlMode.VELOCITY)
    odometry = Odometry(kin)
    odometry.update(np.zeros(kin.n_wheels), dt)
    pose_cmd, pose_odom = np.zeros((len(times), 3)), np.zeros((len(times), 3))
    pose = np.zeros(3)
    for k in range(len(times)):
        pose = integrate_pose(pose, twists[k], dt)
        pose_cmd[k] = pose
        pose_odom[k] = odometry.update(result['position'][k], dt)
    return {'time': times, 'twist_cmd': twists, 'wheel_cmd': wheel_cmd,
            'wheel_speed': kin.to_driver(result['velocity']), 'current': result['current'],
            'pose_cmd': pose_cmd, 'pose_odom': pose_odom}


def summarise(model, script, run_data, wall_time):
    """The text summary printed by the demo."""
    import numpy as np
    names = model.wheel_names
    error = run_data['wheel_speed'] - run_data['wheel_cmd']
    lines = [f'youbot-fdi simulate: model simulation, profile {model.profile.name!r}, '
             f'{script.duration:.1f} s of driving at {1.0 / model.firmware.period:g} Hz '
             f'({wall_time:.2f} s wall time)', '', 'script:']
    start = 0.0
    for segment in script.segments:
        wheels = model.kinematics.to_driver(model.kinematics.inverse(segment.twist))
        lines.append(f'  {start:5.1f} s  {segment.name:<12} twist {np.array(segment.twist)}  '
                     f'-> wheels {np.round(wheels, 2)} rad/s')
        start += segment.duration
    lines += ['', f'{"wheel":<16}{"RMS speed error":>18}{"max |error|":>14}{"peak |current|":>16}',
              f'{"":<16}{"[rad/s]":>18}{"[rad/s]":>14}{"[A]":>16}']
    for i, name in enumerate(names):
        lines.append(f'{name:<16}{np.sqrt(np.mean(error[:, i] ** 2)):>18.4f}'
                     f'{np.max(np.abs(error[:, i])):>14.4f}'
                     f'{np.max(np.abs(run_data["current"][:, i])):>16.3f}')
    final_cmd, final_odom = run_data['pose_cmd'][-1], run_data['pose_odom'][-1]
    gap = np.hypot(*(final_odom[:2] - final_cmd[:2]))
    lines += ['', f'final pose commanded  x {final_cmd[0]:+.3f} m  y {final_cmd[1]:+.3f} m  '
                  f'yaw {np.degrees(final_cmd[2]):+.1f} deg',
              f'final pose odometry   x {final_odom[0]:+.3f} m  y {final_odom[1]:+.3f} m  '
              f'yaw {np.degrees(final_odom[2]):+.1f} deg  ({gap * 100:.1f} cm from commanded: '
              'the velocity loop lags the steps)']
    return '\n'.join(lines)


def plot(model, run_data, path):
    """Write the demo figure; returns the path or None when matplotlib is missing."""
    try:
        import matplotlib
        matplotlib.use('Agg')
        import matplotlib.pyplot as plt
    except ImportError:
        return None
    t = run_data['time']
    fig, axes = plt.subplots(2, 2, figsize=(12, 8), constrained_layout=True)
    colors = plt.rcParams['axes.prop_cycle'].by_key()['color']
    for i, name in enumerate(model.wheel_names):
        axes[0, 0].plot(t, run_data['wheel_cmd'][:, i], '--', color=colors[i], lw=1)
        axes[0, 0].plot(t, run_data['wheel_speed'][:, i], color=colors[i], lw=1.2, label=name)
        axes[1, 0].plot(t, run_data['current'][:, i], color=colors[i], lw=1, label=name)
    axes[0, 0].set(title='wheel speed: command (dashed) and simulated (driver convention)',
                   xlabel='time [s]', ylabel='[rad/s]')
    axes[0, 0].legend(fontsize=8)
    axes[1, 0].set(title='motor current from the firmware velocity loop', xlabel='time [s]',
                   ylabel='[A]')
    axes[0, 1].plot(run_data['pose_cmd'][:, 0], run_data['pose_cmd'][:, 1], '--', label='commanded')
    axes[0, 1].plot(run_data['pose_odom'][:, 0], run_data['pose_odom'][:, 1], label='odometry')
    axes[0, 1].set(title='path in the odom frame', xlabel='x [m]', ylabel='y [m]', aspect='equal')
    axes[0, 1].legend(fontsize=8)
    for j, label in enumerate(('v_x [m/s]', 'v_y [m/s]', 'w_z [rad/s]')):
        axes[1, 1].plot(t, run_data['twist_cmd'][:, j], color=colors[j], lw=1, label=label)
    axes[1, 1].set(title='commanded base twist', xlabel='time [s]')
    axes[1, 1].legend(fontsize=8)
    fig.suptitle(f'youbot-fdi simulate: profile {model.profile.name}')
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def run(args):
    from youbot_fdi.model.profile import load_model
    from youbot_fdi.model.scenario import load_script
    profile_name, script = load_script(args.script, args.duration)
    model = load_model(args.profile or profile_name)
    started = time.perf_counter()
    run_data = simulate_drive(model, script)
    print(summarise(model, script, run_data, time.perf_counter() - started))
    if not args.no_plot:
        written = plot(model, run_data, Path(args.output_dir) / FIGURE_NAME)
        print(f'\nfigure: {written}' if written else
              '\nfigure skipped: matplotlib is not installed (pip install "youbot_fdi[plot]")')
    return 0
