"""``youbot-fdi echo``: print the fault events published on /youbot_fdi/faults, one JSON line each.

The topic is latched (transient-local), so the last fault state arrives even if it was published
before echo started. On a robot ``ros2 topic echo /youbot_fdi/faults`` works too.
"""
from youbot_fdi.topics import FAULTS

NAME = 'echo'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='print fault events from /youbot_fdi/faults (JSON lines)',
        description='Subscribe to /youbot_fdi/faults (latched) and print each fault event as a '
                    'JSON line (the --events format). Stops after --count events or --timeout s.')
    parser.add_argument('--count', type=int, default=0, help='stop after this many events (0: never)')
    parser.add_argument('--timeout', type=float, default=0.0, help='stop after this many seconds (0: never)')
    parser.add_argument('--topic', default=FAULTS)
    parser.add_argument('--events', help='also write the events here (JSON lines, each flushed as '
                                         'it arrives)')
    parser.set_defaults(run=run)


def run(args):
    from contextlib import nullcontext

    from youbot_fdi.app.eventlog import EventLog
    from youbot_fdi.nodes.echo import echo_faults
    with (EventLog(args.events) if args.events else nullcontext()) as log:
        def write(event):
            print(event.to_json(), flush=True)
            if log is not None:
                log.write(event)
        echo_faults(args.topic, args.count, args.timeout, write=write)
    return 0
