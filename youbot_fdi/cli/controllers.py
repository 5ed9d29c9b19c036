"""``youbot-fdi controllers``: the firmware PI against the host-side model-based controller."""
from pathlib import Path
import sys

NAME = 'controllers'
FIGURE_NAME = 'controllers.png'
TABLE_NAME = 'controllers.md'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='compare the firmware PI with the host-side model-based controller',
        description='Drive the demo and the aggressive script (config/demo.yaml, '
                    'config/aggressive.yaml) on the virtual base in lockstep, under the firmware '
                    'PI (velocity mode) and under the host-side model-based controller (current '
                    'mode: inverse-dynamics feedforward plus feedback on the model, '
                    'config/control.yaml), without a fault and with each fault on wheel_joint_fl. '
                    'Prints the table (RMS tracking error against the true body velocity, peak and '
                    'RMS current), writes it as Markdown and a figure. About 80 s on 2 cores.')
    parser.add_argument('--profiles', default='youbot,seed',
                        help='parameter profiles, comma-separated (default: youbot,seed)')
    parser.add_argument('--drives', default='demo.yaml,aggressive.yaml',
                        help='drive scripts under config/, comma-separated (default: both)')
    parser.add_argument('--no-faults', action='store_true', help='fault-free drives only')
    parser.add_argument('--output-dir', default='out/controllers',
                        help='where the table and the figure go (default: out/controllers)')
    parser.add_argument('--no-plot', action='store_true', help='do not write the figure')
    parser.set_defaults(run=run)


def run(args):
    from youbot_fdi.bench.controllers import compare, FAULTS, format_table, plot
    split = lambda text: tuple(v.strip() for v in text.split(',') if v.strip())  # noqa: E731
    faults = (None,) if args.no_faults else FAULTS
    runs = compare(split(args.profiles), split(args.drives), faults,
                   progress=lambda text: print(text, file=sys.stderr, flush=True))
    table = format_table(runs)
    print(table)
    out = Path(args.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / TABLE_NAME).write_text(table + '\n')
    print(f'\ntable: {out / TABLE_NAME}')
    if not args.no_plot:
        written = plot(runs, out / FIGURE_NAME)
        print(f'figure: {written}' if written else
              'figure skipped: matplotlib is not installed (pip install "youbot_fdi[plot]")')
    return 0
