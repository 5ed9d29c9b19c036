"""``youbot-fdi play``: publish a recording live on its topics, with /clock."""
import sys

NAME = 'play'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='publish a rosbag2 recording live on its topics, with /clock',
        description='Publish /joint_states, /wheel_commands, /cmd_vel (and other standard topics) '
                    'of a recording at their recorded pace, with /clock, for nodes started with '
                    'use_sim_time:=true (this machine has no `ros2 bag play`).')
    parser.add_argument('bag', help='rosbag2 directory')
    parser.add_argument('--rate', type=float, default=1.0, help='playback speed factor (default 1)')
    parser.add_argument('--no-clock', action='store_true', help='do not publish /clock')
    parser.add_argument('--topics', nargs='*', help='only these topics')
    parser.set_defaults(run=run)


def run(args):
    from youbot_fdi.nodes.play import play
    if not args.rate > 0:
        print('youbot-fdi play: error: --rate must be > 0', file=sys.stderr)
        return 2
    count = play(args.bag, args.rate, not args.no_clock, args.topics,
                 progress=lambda n: print(f'\r{n} messages', end='', file=sys.stderr, flush=True))
    print(f'\n{args.bag}: published {count} messages')
    return 0
