"""``youbot-fdi bench``: the project's speed figures, as ratios against same-run baselines."""
import sys

from youbot_fdi.bench import format_results, run_all

NAME = 'bench'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='benchmark the model, structural analysis and CAN shim against baselines',
        description='Time the simulator, the structural analysis and the driver shim with the '
                    'virtual base, each against a baseline measured in the same run (printed as '
                    'ratios, so results compare across machines). Takes about 10 s.')
    parser.set_defaults(run=run)


def run(_args):
    results = run_all(progress=lambda text: print(text, file=sys.stderr))
    print(format_results(results))
    return 0
