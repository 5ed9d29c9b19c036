"""``youbot-fdi``: the umbrella command. ``youbot-fdi <command> --help`` explains each command."""
import argparse
import sys

from youbot_fdi import __version__
from youbot_fdi.cli import (bench, controllers, demo, echo, fleet, identify, incidents, model_info, play,
                            record, replay, simulate, structure)
from youbot_fdi.cli.status import ERROR, INTERRUPTED
from youbot_fdi.errors import FdiError

COMMANDS = (demo, identify, replay, incidents, fleet, record, play, echo, simulate, controllers, structure,
            model_info, bench)


def build_parser():
    """The argument parser with every sub-command registered."""
    parser = argparse.ArgumentParser(
        prog='youbot-fdi',
        description='Fault detection and isolation for omnidirectional mecanum bases (KUKA youBot).')
    parser.add_argument('--version', action='version', version=f'%(prog)s {__version__}')
    subparsers = parser.add_subparsers(dest='command', metavar='COMMAND')
    for command in COMMANDS:
        command.add_parser(subparsers)
    return parser


def main(argv=None):
    """Entry point; returns the process exit status."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return args.run(args) or 0
    except (FdiError, FileNotFoundError) as err:
        print(f'youbot-fdi {args.command}: error: {err}', file=sys.stderr)
        return ERROR
    except KeyboardInterrupt:
        return INTERRUPTED


if __name__ == '__main__':
    sys.exit(main())
