"""``youbot-fdi model``: print a profile's model (kinematics, mass matrix, modes, loop stability)."""
from youbot_fdi.config_paths import available_profiles

NAME = 'model'


def add_parser(subparsers):
    parser = subparsers.add_parser(
        NAME, help='print the kinematic and dynamic model of a parameter profile',
        description='Print the Jacobian (eq. 3.8), forward kinematics (eq. 3.11), mass matrix, '
                    'free-motion time constants and sampled velocity-loop stability of a profile.')
    parser.add_argument('--profile', default='youbot',
                        help=f"profile name ({', '.join(available_profiles())}) or a YAML path "
                             '(default: youbot)')
    parser.set_defaults(run=run)


def run(args):
    import numpy as np

    from youbot_fdi.model.firmware import sampled_loop_spectral_radius
    from youbot_fdi.model.profile import load_model
    model = load_model(args.profile)
    dyn = model.dynamics
    np.set_printoptions(precision=5, suppress=False, linewidth=110)
    print(f'profile {model.profile.name}: {model.profile.description}')
    print(f'source: {model.profile.source}')
    print('wheels:', ', '.join(f'{w.name} (sign {w.drive_sign:+.0f})' for w in model.platform.wheels))
    print('\ninverse kinematics J [rad/s per (m/s, m/s, rad/s)], kinematic convention:')
    print(model.kinematics.jacobian)
    print('\nforward kinematics J+ :')
    print(model.kinematics.forward_matrix)
    print('\nmass matrix M [kg·m²]:')
    print(dyn.mass_matrix)
    print(f'\ncond(M) = {np.linalg.cond(dyn.mass_matrix):.4g}')
    print('free-motion time constants [s]:', dyn.time_constants())
    radius = sampled_loop_spectral_radius(dyn, model.drive.torque_per_amp, model.firmware)
    verdict = 'stable' if radius < 1.0 else 'UNSTABLE'
    print(f'sampled velocity loop at {1.0 / model.firmware.period:g} Hz: spectral radius '
          f'{radius:.4g} ({verdict}); profile runs it as {model.firmware.loop.value}')
    return 0
