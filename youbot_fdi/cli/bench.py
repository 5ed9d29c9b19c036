"""``youbot-fdi bench``: the project's speed figures, as ratios against same-run baselines."""
import sys

NAME = 'bench'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='benchmark speed against same-run baselines, or (--faults) the FDI itself',
        description='Time the simulator, the structural analysis, the driver shim with the '
                    'virtual base, replay and the live FDI path, and the node suite, each against '
                    'a baseline measured in the same run (printed as ratios, so results compare '
                    'across machines); also the CLI start time, the CAN fuzz (100,000 frames), the '
                    'learned correction, identify and the fleet on Dask. Takes about 9 minutes. '
                    'With --faults: the fault benchmark (detection, isolation, delays, false '
                    'alarms per hour, the closest two events of one component) on four suites side '
                    'by side: the project\'s virtual base (both control modes, with replay speed '
                    'against decode-only), an independently written simulator, a cross-validation '
                    'on the real Robotino recordings in shared/ (worst fold first), and randomized '
                    'plants written apart from the FDI\'s model, each replayed with the learned '
                    'and the physics-only parameters (the ablation table). With --live: the live '
                    'soak.')
    parser.add_argument('--faults', action='store_true',
                        help='run the fault benchmark instead: its suites (see --suites), each '
                             'calibrated with identify as a user would (on 2 cores: about 25 '
                             'minutes without the randomized suite, which adds about 15 per 50 '
                             'plants)')
    parser.add_argument('--live', action='store_true',
                        help='run the live soak instead: youbot-fdi demo as a user runs it, the '
                             'fault-free drive for --soak-minutes alone and beside a busy core '
                             '(alarms, the shim\'s late cycles), then every demo fault on every '
                             'wheel both ways (first alarm on the right wheel?); about 40 minutes')
    parser.add_argument('--soak-minutes', type=float, default=10.0,
                        help='length of each live soak [min] (default: 10)')
    parser.add_argument('--variations', type=int, default=3,
                        help='plants in the fault benchmark, the nominal one first (default: 3)')
    parser.add_argument('--seed', type=int, default=0, help='random seed of the fault benchmark')
    parser.add_argument('--workers', type=int, default=2, help='processes (default: 2)')
    parser.add_argument('--modes', default='velocity,effort',
                        help='control modes of the fault benchmark, comma-separated '
                             '(default: velocity,effort)')
    parser.add_argument('--suites', default='simulated,independent,real,randomized',
                        help="fault benchmark suites, comma-separated: simulated (the project's "
                             'virtual base), independent (an independently written simulator), '
                             'real (cross-validation on the Robotino recordings in '
                             'shared/real_data/robotino, or $YOUBOT_FDI_ROBOTINO_DATA; skipped when '
                             "absent), randomized (hundreds of plants written apart from the FDI's "
                             'model, each calibrated on its own gentle drive) (default: all)')
    parser.add_argument('--plants', type=int, default=200,
                        help='plants of the randomized suite (default: 200: 20 h of fault-free '
                             'driving)')
    parser.set_defaults(run=run)


def run(args):
    progress = lambda text: print(text, file=sys.stderr, flush=True)  # noqa: E731
    if args.faults:
        return run_faults(args, progress)
    if args.live:
        from youbot_fdi.bench.live import run_live
        print(run_live(progress, args.soak_minutes), flush=True)
        return 0
    from youbot_fdi.bench.speed import format_results, run_all
    print(format_results(run_all(progress=progress)))
    return 0


SUITES = ('simulated', 'independent', 'real', 'randomized')


def run_faults(args, progress):
    """The fault benchmark's suites, each printed as it finishes, side by side in one format."""
    import tempfile
    from youbot_fdi.bench import crossval, independent, robotino
    from youbot_fdi.bench.calibration import VARIANTS
    from youbot_fdi.bench.scoring import ablation, summarise
    from youbot_fdi.bench.simulated import MODES, run_fault_benchmark, summarise as summarise_simulated
    modes = tuple(m.strip() for m in args.modes.split(',') if m.strip())
    suites = tuple(s.strip() for s in args.suites.split(',') if s.strip())
    if set(modes) - set(MODES) or not modes or set(suites) - set(SUITES) or not suites:
        print(f'youbot-fdi bench: error: --modes takes {",".join(MODES)} and --suites '
              f'{",".join(SUITES)}; got {args.modes!r}, {args.suites!r}', file=sys.stderr)
        return 2
    rows = []  # the ablation table: (suite, variant, results, spread)
    with tempfile.TemporaryDirectory(prefix='youbot_fdi_bench_') as workdir:
        if 'simulated' in suites:
            plants, results, spread = run_fault_benchmark(args.variations, args.seed, args.workers,
                                                          progress, modes=modes)
            print(summarise_simulated(plants, results[VARIANTS[0]]), flush=True)
            rows += [('simulated', v, results[v], spread) for v in VARIANTS]
        if 'independent' in suites:
            line, results, spread = independent.run_suite(workdir, progress, args.workers, args.seed)
            print('\n' + summarise(f'Independent youBot simulator (both modes; {line})',
                                   results[VARIANTS[0]]), flush=True)
            rows += [('independent', v, results[v], spread) for v in VARIANTS]
        if 'real' in suites:
            folds = crossval.run_crossval(workdir, progress, args.workers)
            if folds is None:
                print(f'\nReal data (Robotino): skipped, no data at {robotino.DEFAULT_DATA} '
                      f'(set ${robotino.ENV_DATA})', flush=True)
            else:
                print('\n' + crossval.summarise_folds(folds, VARIANTS[0]), flush=True)
                rows += [('real', v, [r for f in folds for r in f.results[v]],
                          folds[0].calibration['spread']) for v in VARIANTS]
        if 'randomized' in suites:
            from youbot_fdi.bench import randomized
            plants, scored, identified = randomized.run_suite(workdir, progress, args.workers,
                                                              args.seed, args.plants)
            print('\n' + randomized.summarise(plants, scored), flush=True)
            print('\n' + randomized.identification_table(plants, identified), flush=True)
    print('\n' + ablation(rows), flush=True)
    return 0
