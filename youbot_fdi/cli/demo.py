"""``youbot-fdi demo``: the main job, live: a virtual youBot, the driver shim and every FDI node."""
from youbot_fdi.faults import INJECTABLE

NAME = 'demo'
DEFAULT_FAULT = 'torque_loss'
DEFAULT_WHEEL = 'wheel_joint_fr'
DEFAULT_AT = 5.0  # [s]
NONE = 'none'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='the live demo: virtual youBot, driver shim and FDI nodes over ROS 2 topics',
        description='Run a virtual youBot on a virtual CAN bus, the driver shim and every FDI node '
                    '(kinematics_bridge, observer, residual_generator, decision) as separate '
                    'ROS 2 processes, drive the scripted path (config/demo.yaml), inject a '
                    'fault (default: torque_loss on wheel_joint_fr at 5 s; --fault none for a '
                    'fault-free drive) and show it as it is detected. Ends by itself.')
    parser.add_argument('--fault', default=DEFAULT_FAULT,
                        choices=[NONE] + [k.value for k in INJECTABLE])
    parser.add_argument('--wheel', default=DEFAULT_WHEEL, help='faulty wheel (joint name)')
    parser.add_argument('--at', type=float, default=DEFAULT_AT, help='fault onset [s into the drive]')
    parser.add_argument('--duration', type=float, help='stretch the drive to this many seconds')
    parser.add_argument('--events', help='write the fault events seen on /youbot_fdi/faults here')
    parser.add_argument('--script', help='drive script YAML (default: config/demo.yaml)')
    parser.add_argument('--record', metavar='DIR',
                        help='also record /joint_states and /wheel_commands as a rosbag2 recording')
    layout = parser.add_mutually_exclusive_group()
    layout.add_argument('--composed', dest='layout', action='store_const', const='composed',
                        help='the FDI nodes in this process and executor (youbot_fdi_suite)')
    layout.add_argument('--fused', dest='layout', action='store_const', const='fused',
                        help='as --composed, the observer computing the residuals itself '
                             '(youbot_fdi_fused)')
    parser.set_defaults(layout='separate')
    parser.add_argument('--quiet', action='store_true', help='only the summary')
    parser.set_defaults(run=run)


def run(args):
    from youbot_fdi.model.scenario import load_script
    from youbot_fdi.nodes.demo import DemoPlan, run_demo
    _, script = load_script(args.script, args.duration)
    fault = None if args.fault == NONE else args.fault
    plan = DemoPlan(script, fault, args.wheel, args.at, console=not args.quiet, record=args.record,
                    layout=args.layout)
    print(f'youbot-fdi demo ({args.layout} FDI nodes): {script.duration:.1f} s drive, '
          + (f'{fault} on {args.wheel} at {args.at:g} s' if fault else 'no fault injected'), flush=True)
    events, injected_at, start = run_demo(plan, args.events)
    alarms = [e for e in events if e.level == 'ERROR']
    print('\nsummary:')
    if fault is None:
        print(f'  fault-free drive: {len(alarms)} alarms' + (' (none expected)' if alarms else ''))
    elif injected_at is None:
        print('  the drive ended before the fault was injected')
    else:
        hits = [e for e in alarms if e.wheel == args.wheel and e.stamp >= injected_at]
        if hits:
            named = ' -> '.join(dict.fromkeys(e.fault for e in hits))
            print(f'  {fault} injected on {args.wheel}: detected on {hits[0].wheel} '
                  f'{(hits[0].stamp - injected_at) * 1000:.0f} ms after injection, named {named}')
        else:
            print(f'  {fault} injected on {args.wheel}: NOT detected')
        others = [e for e in alarms if e.wheel != args.wheel]
        if others:
            print(f'  other alarms: {[(e.wheel, e.fault) for e in others]}')
    if args.events:
        print(f'  events: {args.events} ({len(events)} lines)')
    if args.record:
        print(f'  recording: {args.record} (try: youbot-fdi replay {args.record} --events E.jsonl)')
    return 0
