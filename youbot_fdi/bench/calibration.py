"""Calibration as a user does it, for every fault suite: ``identify`` on one nominal recording,
written as two parameter files, the learned variant (the product's default) and the physics-only
one, so each suite replays every recording with both (the ablation of issue 12).

The two files differ only in the ``learned`` section: the bounds come from the physics residuals
in both (youbot_fdi/fdi/learned.py says why).
"""
from dataclasses import replace

VARIANTS = ('learned', 'physics')  # the first is the product's default


def calibrate(recording, prior, out_stem, settings=None):
    """``identify`` ``recording`` from the ``prior`` model; returns ({variant: parameter file},
    IdentificationResult). Files are written beside ``out_stem`` (``<stem>_<variant>.yaml``)."""
    from youbot_fdi.app.recordings import identify_recording
    from youbot_fdi.fdi.settings import FdiSettings
    from youbot_fdi.model.profile import save_profile
    from youbot_fdi.settings import load_settings
    result = identify_recording(recording, prior, settings or load_settings(FdiSettings, 'fdi'))
    paths = {}
    for variant in VARIANTS:
        profile = result.profile if variant == 'learned' else replace(result.profile, learned=None)
        paths[variant] = str(save_profile(profile, f'{out_stem}_{variant}.yaml'))
    return paths, result


def residual_spread(result):
    """{variant: {family: RMS}} of a calibration's residuals (the same twice when nothing was
    learned), as ``identify`` recorded it."""
    return result.info['learning']['residual_rms']
