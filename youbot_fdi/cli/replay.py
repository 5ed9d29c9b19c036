"""``youbot-fdi replay``: run the whole FDI pipeline offline over a rosbag2 recording."""
from pathlib import Path
import sys
import time

from youbot_fdi.cli.status import DAMAGED
from youbot_fdi.faults import Level
from youbot_fdi.topics import JOINT_STATES, WHEEL_COMMANDS

NAME = 'replay'
PROGRESS_MIN_MESSAGES = 20000  # show a progress bar from this many messages on
PROGRESS_INTERVAL = 0.2  # [s] between redraws of the progress bar


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='run the FDI pipeline offline over a recording; write fault events',
        description='Replay a rosbag2 recording (sqlite3 or mcap) through the same residual '
                    'generator and decision the live nodes use, and write one JSON line per fault '
                    'state change, each written and flushed as it is found. A recording cut short '
                    '(power lost while recording), broken part-way or without metadata.yaml is '
                    'analysed as far as it can be read. Exit status: 0 whether or not faults were '
                    f'found; {DAMAGED} for a damaged recording (its readable part analysed, one '
                    'line saying where it ends and what was lost); 1 with a one-line reason when '
                    'nothing can be read. An incident (a folder `youbot-fdi incidents` lists) is '
                    'replayed with the parameter file and FDI settings the robot ran with, unless '
                    '--params or --fdi-config say otherwise.')
    parser.add_argument('bag', help='rosbag2 directory (or an incident folder)')
    parser.add_argument('--params', help='parameter file from `youbot-fdi identify` (default: the '
                                         "incident's own, else the youbot profile and "
                                         'config/fdi.yaml)')
    parser.add_argument('--events', required=True, help='write fault events here (JSON lines)')
    parser.add_argument('--report', metavar='DIR', help='also write an HTML/PNG report here')
    parser.add_argument('--joint-topic', default=JOINT_STATES)
    parser.add_argument('--command-topic', default=WHEEL_COMMANDS)
    parser.add_argument('--fdi-config', help='FDI settings YAML (default: config/fdi.yaml)')
    parser.set_defaults(run=run)


def _progress(done, total, started):
    fraction = done / total if total else 1.0
    bar = '#' * int(30 * fraction)
    rate = done / max(time.perf_counter() - started, 1e-9)
    print(f'\r[{bar:<30}] {fraction:6.1%} {done}/{total} messages, {rate:,.0f}/s',
          end='', file=sys.stderr, flush=True)


def run_parameters(args):
    """(parameter file, FDI settings file) to replay with: the command line's, else an
    incident's own (what the robot ran with)."""
    from youbot_fdi.app.incidents import incident_parameters, is_incident
    if is_incident(args.bag) and not args.params and not args.fdi_config:
        params, fdi_config = incident_parameters(args.bag)
        print(f'{args.bag}: an incident; replayed with its own parameters '
              f'({params or "the profile defaults"}, {fdi_config or "config/fdi.yaml"})')
        return params, fdi_config
    return args.params, args.fdi_config


def run(args):
    from youbot_fdi.bag.reader import RecordingError
    from youbot_fdi.app.eventlog import EventLog
    from youbot_fdi.app.config import build_pipeline
    from youbot_fdi.app.replay import replay_recording
    from youbot_fdi.fdi.observer import STAMP_COUNTERS
    params, fdi_config = run_parameters(args)
    model, pipeline = build_pipeline(params, fdi_config, keep_frames=bool(args.report))
    events_path = Path(args.events)
    found = []
    error = None
    started = time.perf_counter()
    with EventLog(events_path) as log:
        def keep(event):
            log.write(event)
            found.append(event)

        drawn = [0.0]

        def progress(done, total):  # called after each chunk of messages
            now = time.perf_counter()
            if total >= PROGRESS_MIN_MESSAGES and sys.stderr.isatty() \
                    and (now - drawn[0] >= PROGRESS_INTERVAL or done == total):
                drawn[0] = now
                _progress(done, total, started)
                if done == total:
                    print(file=sys.stderr)

        try:
            result = replay_recording(pipeline, args.bag, args.joint_topic, args.command_topic, keep, progress)
        except RecordingError as err:
            error = err
    elapsed = time.perf_counter() - started
    if error is not None:
        print(f'youbot-fdi replay: error: {error} ({len(found)} events kept in {events_path})',
              file=sys.stderr)
        return 1
    alarms = [e for e in found if e.level == Level.ERROR]
    counters = result.counters
    if result.damage is not None:
        print(f'{args.bag}: {result.damage.describe()}', file=sys.stderr)
    print(f'{args.bag}: {counters["joint_states"]} joint states, {counters["wheel_commands"]} '
          f'commands in {elapsed:.2f} s; {len(alarms)} alarms, {len(found)} events -> {events_path}')
    skipped = {k: v for k, v in counters.items() if k.startswith('skipped') and v}
    if skipped:
        print(f'skipped messages: {skipped}')
    restarts = {k: v for k, v in counters.items() if k in STAMP_COUNTERS and v}
    if restarts:
        print(f'samples that restarted the residuals: {restarts}')
    if not result.has_commands:
        print(f'note: no {args.command_topic}: faults in the command path (runaway) cannot be seen')
    for event in alarms:
        print(f'  {event.stamp:.3f} {event.level} {event.wheel} {event.fault}')
    if args.report:
        from youbot_fdi.app.report import write_report
        index = write_report(Path(args.report), model, pipeline, found, args.bag)
        print(f'report: {index}')
    return DAMAGED if result.damage is not None and result.damage.lost else 0
