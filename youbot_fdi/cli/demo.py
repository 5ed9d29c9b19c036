"""``youbot-fdi demo``: the main job, live: a virtual youBot, the driver shim and every FDI node."""
import sys

from youbot_fdi.faults import INJECTABLE, Level

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
    parser.add_argument('--repeat', type=int, default=1, metavar='N',
                        help='drive the script N times in a row (a soak; default: 1)')
    parser.add_argument('--events', help='write the fault events seen on /youbot_fdi/faults here')
    parser.add_argument('--script', help='drive script YAML (default: config/demo.yaml)')
    parser.add_argument('--record', metavar='DIR',
                        help='also record /joint_states and /wheel_commands of the drive (from its start) '
                             'as a rosbag2 recording')
    layout = parser.add_mutually_exclusive_group()
    layout.add_argument('--composed', dest='layout', action='store_const', const='composed',
                        help='the FDI nodes in this process and executor (youbot_fdi_suite)')
    layout.add_argument('--fused', dest='layout', action='store_const', const='fused',
                        help='as --composed, the observer computing the residuals itself '
                             '(youbot_fdi_fused)')
    parser.set_defaults(layout='separate')
    parser.add_argument('--torque-loss-gain', type=float, metavar='G',
                        help='delivered over commanded torque under torque_loss (default: '
                             'config/virtual_youbot.yaml, 0.3; 0 is a dead motor)')
    parser.add_argument('--friction-factor', type=float, metavar='F',
                        help='viscous friction multiplier under friction (default: '
                             'config/virtual_youbot.yaml, 6)')
    parser.add_argument('--max-wheel-speed', type=float, metavar='W',
                        help="the kinematics bridge's wheel-speed limit [rad/s] (default: "
                             'config/kinematics_bridge.yaml, 10, the URDF limit)')
    parser.add_argument('--degraded-max-wheel-speed', type=float, metavar='W',
                        help="its limit while driving degraded (--react) [rad/s] (default: "
                             "config/reactions.yaml, 16.2, the firmware's maximum positioning "
                             'velocity)')
    parser.add_argument('--react', action='store_true',
                        help='the kinematics bridge applies the fault reactions of '
                             'config/reactions.yaml (motor off, stop, degraded driving, '
                             'substituted readings); they are INFO lines in --events')
    parser.add_argument('--summary', metavar='S.json',
                        help="write the run's figures as JSON (detection delay, reactions, RMS "
                             "body-velocity tracking error from the fault to the end against the "
                             "simulator's true velocity; a fault-free drive from --at, the floor), to "
                             'compare runs with and without --react')
    parser.add_argument('--incidents', metavar='DIR', default='',
                        help='where the decision node keeps an incident recording of each alarm '
                             'episode (default: $ROS_HOME/youbot_fdi/incidents; ROS_HOME defaults '
                             'to ~/.ros); list them with `youbot-fdi incidents DIR`')
    parser.add_argument('--incident-max-count', type=int, default=0, metavar='N',
                        help='incidents the folder keeps, the oldest going first (default: '
                             'config/incidents.yaml, 20)')
    parser.add_argument('--quiet', action='store_true', help='only the summary')
    parser.set_defaults(run=run)


def tracking_window(args, run):
    """(start [s], what it is) of the tracking error's window: from the fault's injection; a
    fault-free drive from ``--at``, the window a fault there would have (the floor it sets); a
    fault never injected over the whole drive."""
    if run.injected_at is not None:
        return run.injected_at, 'fault injection'
    if args.fault == NONE:
        return run.start + args.at, f'{args.at:g} s into the drive'
    return run.start, 'drive start'


def write_summary(path, args, run, alarms, tracking):
    """The run's figures as one JSON object."""
    import json
    from pathlib import Path
    first = next((e for e in alarms if run.injected_at is not None and e.stamp >= run.injected_at), None)
    summary = {
        'fault': args.fault, 'wheel': args.wheel, 'at': args.at, 'layout': args.layout,
        'react': args.react, 'fault_settings': plan_fault_settings(args),
        'max_wheel_speed': args.max_wheel_speed,
        'degraded_max_wheel_speed': args.degraded_max_wheel_speed,
        'detected': first is not None and first.wheel == args.wheel,
        'detection_delay_s': None if first is None else round(first.stamp - run.injected_at, 4),
        'alarms': [e.to_dict() for e in alarms],
        'reactions': [r.to_dict() for r in run.reactions],
        'before_drive': [item.to_dict() for item in run.before_drive],
        'tracking_rms_linear_mps': None if tracking is None else round(tracking[0], 5),
        'tracking_rms_angular_radps': None if tracking is None else round(tracking[1], 5),
        'tracking_from': tracking_window(args, run)[1],
        'drive_start': run.start, 'injected_at': run.injected_at,
        'shim': run.shim, 'shim_startup': run.shim_startup,
    }
    Path(path).write_text(json.dumps(summary, indent=2) + '\n')


def bridge_overrides(args):
    """The kinematics bridge's (name, value) parameter overrides of the command line."""
    return tuple((name, getattr(args, name)) for name in ('max_wheel_speed', 'degraded_max_wheel_speed')
                 if getattr(args, name) is not None)


def plan_fault_settings(args):
    """The virtual base's fault magnitudes the command line overrides (name -> value)."""
    chosen = {'torque_loss_gain': args.torque_loss_gain, 'friction_factor': args.friction_factor}
    return {name: value for name, value in chosen.items() if value is not None}


def run(args):
    from youbot_fdi.app.incidents import IncidentSettings, list_incidents
    from youbot_fdi.model.scenario import load_script
    from youbot_fdi.nodes.demo import DemoPlan, run_demo
    if args.repeat < 1:
        print(f'youbot-fdi demo: error: --repeat takes a count >= 1, got {args.repeat}', file=sys.stderr)
        return 1
    _, script = load_script(args.script, args.duration)
    script = script.repeated(args.repeat)
    fault = None if args.fault == NONE else args.fault
    plan = DemoPlan(script, fault, args.wheel, args.at, console=not args.quiet, record=args.record,
                    layout=args.layout, react=args.react,
                    base_overrides=tuple(plan_fault_settings(args).items()),
                    bridge_overrides=bridge_overrides(args), incident_dir=args.incidents,
                    incident_max_count=args.incident_max_count)
    incident_folder = IncidentSettings(incident_dir=args.incidents).folder()
    incidents_before = {i.path for i in list_incidents(incident_folder)}
    print(f'youbot-fdi demo ({args.layout} FDI nodes): {script.duration:.1f} s drive, '
          + (f'{fault} on {args.wheel} at {args.at:g} s' if fault else 'no fault injected'), flush=True)
    run = run_demo(plan, args.events)
    events, injected_at = run.events, run.injected_at
    alarms = [e for e in events if e.level == Level.ERROR]
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
    since, window = tracking_window(args, run)
    tracking = run.tracking_error(since)
    if tracking is not None:
        print(f'  RMS tracking error from {window}: {tracking[0]:.3f} m/s, {tracking[1]:.3f} rad/s')
    if run.reactions:
        print('  reactions: ' + ', '.join(f'{r.action} ({r.wheel or "base"})' for r in run.reactions))
    shim = run.shim
    print(f"  driver shim: {shim['cycles']} cycles, lateness p99 {shim['lateness_p99']:.1f} ms, "
          f"max {shim['lateness_max']:.1f} ms; {shim['late_cycles']} past the modules' "
          f"{shim['controller_timeout_ms']:g} ms timeout; {shim['incomplete_cycles']} module "
          'answers missing')
    if run.shim_startup and run.shim_startup['late_cycles']:
        print(f"  driver shim before the drive (the FDI nodes connecting): "
              f"{run.shim_startup['late_cycles']} late cycles, lateness max "
              f"{run.shim_startup['lateness_max']:.1f} ms")
    if run.before_drive:
        print('  before the drive, while the nodes started (not counted above): '
              + ', '.join(f'{getattr(e, "action", None) or e.level} {e.wheel or "base"}: {e.fault}'
                          for e in run.before_drive))
    if run.node_logs:
        print(f'  FDI node logs kept in {run.node_logs}: a process did not stop cleanly '
              f'(exit codes {run.node_exits})')
    if args.summary:
        write_summary(args.summary, args, run, alarms, tracking)
        print(f'  summary: {args.summary}')
    if args.events:
        print(f'  events: {args.events} '
              f'({len(events) + len(run.reactions) + len(run.before_drive)} lines)')
    if args.record:
        print(f'  recording: {args.record} (try: youbot-fdi replay {args.record} --events E.jsonl)')
    incidents = [i for i in list_incidents(incident_folder) if i.path not in incidents_before]
    if incidents:
        print(f'  incidents: {len(incidents)} new in {incident_folder} (try: youbot-fdi incidents '
              f'{incident_folder})')
    return 0
