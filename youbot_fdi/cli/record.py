"""``youbot-fdi record``: record a simulated drive (optionally with a fault) as a rosbag2 recording."""
from youbot_fdi.faults import INJECTABLE

NAME = 'record'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='record a simulated drive (with an optional fault) as a rosbag2 recording',
        description='Drive a virtual youBot through the driver shim over a virtual CAN bus and '
                    'record /joint_states and /wheel_commands (CONTRACT.md), e.g. to try '
                    '`identify` and `replay`.')
    parser.add_argument('output', help='new recording directory')
    parser.add_argument('--script', help='drive script YAML (default: config/demo.yaml)')
    parser.add_argument('--duration', type=float, help='stretch the script to this many seconds')
    parser.add_argument('--mode', choices=('velocity', 'effort'), default='velocity',
                        help='command wheel speeds or open-loop efforts (default: velocity)')
    parser.add_argument('--fault', choices=[k.value for k in INJECTABLE])
    parser.add_argument('--wheel', default='wheel_joint_fl', help='faulty wheel (joint name)')
    parser.add_argument('--at', type=float, default=5.0, help='fault onset [s into the drive]')
    parser.add_argument('--storage', choices=('sqlite3', 'mcap'), default='sqlite3')
    parser.add_argument('--profile', default='youbot', help='the simulated plant (default: youbot)')
    parser.set_defaults(run=run)


def run(args):
    from youbot_fdi.model.profile import load_model
    from youbot_fdi.model.scenario import load_script
    from youbot_fdi.tmcm.recordings import record_drive
    _, script = load_script(args.script, args.duration)
    truth = record_drive(args.output, load_model(args.profile), script, mode=args.mode,
                         fault=args.fault, wheel=args.wheel if args.fault else None,
                         fault_time=args.at, storage=args.storage)
    onset = f', {truth.fault.value} on {truth.wheel} at stamp {truth.onset:.3f}' if truth.fault else ''
    print(f'{args.output}: {truth.duration:.1f} s, {truth.mode} mode{onset}')
    return 0
