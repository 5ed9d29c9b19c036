"""``youbot-fdi bench``: the project's speed figures, as ratios against same-run baselines."""
import sys

from youbot_fdi.bench import format_results, run_all

NAME = 'bench'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='benchmark speed against same-run baselines, or (--faults) the FDI itself',
        description='Time the simulator, the structural analysis, the driver shim with the '
                    'virtual base, replay and the live FDI path, and the node suite, each against '
                    'a baseline measured in the same run (printed as ratios, so results compare '
                    'across machines). Takes about 30 s. With --faults: the fault benchmark '
                    '(detection, isolation, delays, false alarms per hour, replay speed against '
                    'decode-only) in both control modes.')
    parser.add_argument('--faults', action='store_true',
                        help='run the fault benchmark instead: every fault on every wheel on '
                             'randomly varied plants, calibrated with identify (about 7 minutes '
                             'on 2 cores)')
    parser.add_argument('--variations', type=int, default=3,
                        help='plants in the fault benchmark, the nominal one first (default: 3)')
    parser.add_argument('--seed', type=int, default=0, help='random seed of the fault benchmark')
    parser.add_argument('--workers', type=int, default=2, help='processes (default: 2)')
    parser.add_argument('--modes', default='velocity,effort',
                        help='control modes of the fault benchmark, comma-separated '
                             '(default: velocity,effort)')
    parser.set_defaults(run=run)


def run(args):
    progress = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    if args.faults:
        from youbot_fdi.fault_bench import MODES, run_fault_benchmark, summarise
        modes = tuple(m.strip() for m in args.modes.split(',') if m.strip())
        unknown = set(modes) - set(MODES)
        if unknown or not modes:
            print(f'youbot-fdi bench: error: --modes takes {",".join(MODES)}, got {args.modes!r}',
                  file=sys.stderr)
            return 2
        plants, results = run_fault_benchmark(args.variations, args.seed, args.workers, progress,
                                              modes=modes)
        print(summarise(plants, results))
        return 0
    print(format_results(run_all(progress=progress)))
    return 0
