"""``youbot-fdi replay``: run the whole FDI pipeline offline over a rosbag2 recording."""
from pathlib import Path
import sys
import time

from youbot_fdi.topics import JOINT_STATES, WHEEL_COMMANDS

NAME = 'replay'
PROGRESS_MIN_MESSAGES = 20000  # show a progress bar from this many messages on
PROGRESS_INTERVAL = 0.2  # [s] between redraws of the progress bar


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='run the FDI pipeline offline over a recording; write fault events',
        description='Replay a rosbag2 recording (sqlite3 or mcap) through the same residual '
                    'generator and decision the live nodes use, and write one JSON line per fault '
                    'state change. Exit status 0 whether or not faults were found; 1 with a '
                    'one-line reason on unreadable input (events found before are kept).')
    parser.add_argument('bag', help='rosbag2 directory')
    parser.add_argument('--params', help='parameter file from `youbot-fdi identify` (default: the '
                                         'youbot profile and config/fdi.yaml)')
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


def run(args):
    from youbot_fdi.bag.reader import RecordingError
    from youbot_fdi.fdi.pipeline import build_pipeline
    model, pipeline = build_pipeline(args.params, args.fdi_config, keep_frames=bool(args.report))
    events_path = Path(args.events)
    events_path.parent.mkdir(parents=True, exist_ok=True)
    found = []
    error = None
    started = time.perf_counter()
    with events_path.open('w') as events_file:
        def keep(event):
            events_file.write(event.to_json() + '\n')
            events_file.flush()
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
            result = pipeline.replay(args.bag, args.joint_topic, args.command_topic, keep, progress)
        except RecordingError as err:
            error = err
    elapsed = time.perf_counter() - started
    if error is not None:
        print(f'youbot-fdi replay: error: {error} ({len(found)} events kept in {events_path})',
              file=sys.stderr)
        return 1
    alarms = [e for e in found if e.level == 'ERROR']
    counters = result.counters
    print(f'{args.bag}: {counters["joint_states"]} joint states, {counters["wheel_commands"]} '
          f'commands in {elapsed:.2f} s; {len(alarms)} alarms, {len(found)} events -> {events_path}')
    skipped = {k: v for k, v in counters.items() if k.startswith('skipped') and v}
    if skipped:
        print(f'skipped messages: {skipped}')
    if not result.has_commands:
        print(f'note: no {args.command_topic}: faults in the command path (runaway) cannot be seen')
    for event in alarms:
        print(f'  {event.stamp:.3f} {event.level} {event.wheel} {event.fault}')
    if args.report:
        from youbot_fdi.fdi.report import write_report
        index = write_report(Path(args.report), model, pipeline, found, args.bag)
        print(f'report: {index}')
    return 0
