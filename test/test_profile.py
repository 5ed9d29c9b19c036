"""Parameter profiles: the shipped ones load; broken files give a clear error naming the key."""
import copy

import pytest
import yaml

from youbot_fdi.errors import ConfigError
from youbot_fdi.model import available_profiles, load_profile, parse_profile
from youbot_fdi.model.profile import profile_path, profile_to_dict

pytestmark = pytest.mark.fast  # `make check`: the unit tests of the core, under a minute


def test_shipped_profiles_load():
    assert {'seed', 'youbot', 'omni3_example'} <= set(available_profiles())
    seed = load_profile('seed')
    assert seed.dynamics.wheel_inertia == (1.35e-6,) * 4
    assert seed.dynamics.yaw_inertia == 5.5e-6
    assert seed.dynamics.mass == 23.58
    assert seed.platform.names == ('wheel_joint_fl', 'wheel_joint_fr', 'wheel_joint_bl',
                                   'wheel_joint_br')
    assert seed.platform.drive_signs == (-1.0, 1.0, -1.0, 1.0)


def test_profile_round_trips_through_a_mapping():
    profile = load_profile('youbot')
    again = parse_profile(profile_to_dict(profile), source='round trip')
    assert again.dynamics == profile.dynamics
    assert again.drive == profile.drive
    assert again.firmware == profile.firmware
    for a, b in zip(again.platform.wheels, profile.platform.wheels):
        assert a.name == b.name and a.x == pytest.approx(b.x)
        assert a.roller_angle == pytest.approx(b.roller_angle)


def test_the_loops_inertias_round_trip_and_are_left_out_where_not_given():
    """``dynamics.loop_inertias`` (identify writes them where the readings do not see the wheels
    accelerate): a mapping of mass and inertias that comes back as it went; a profile without
    them writes none."""
    from dataclasses import replace
    profile = load_profile('youbot')
    assert profile.dynamics.loop_inertias == () and 'loop_inertias' not in profile_to_dict(profile)['dynamics']
    looped = replace(profile, dynamics=replace(profile.dynamics, loop_inertias=(23.58, 0.945, 0.00946)))
    written = profile_to_dict(looped)['dynamics']['loop_inertias']
    assert written == {'mass': 23.58, 'yaw_inertia': 0.945, 'wheel_inertia': 0.00946}
    assert parse_profile(profile_to_dict(looped), source='round trip').dynamics == looped.dynamics


@pytest.fixture()
def youbot_dict():
    return yaml.safe_load(profile_path('youbot').read_text())


def _edit(data, path, value):
    data = copy.deepcopy(data)
    *parents, last = path
    target = data
    for key in parents:
        target = target[key]
    if value is _DELETE:
        del target[last]
    else:
        target[last] = value
    return data


_DELETE = object()


@pytest.mark.parametrize('path, value, match', [
    (('dynamics', 'mass'), _DELETE, r'dynamics\.mass is missing'),
    (('dynamics', 'wheel_inertia'), -1e-3, r'dynamics\.wheel_inertia\[0\] must be > 0'),
    (('dynamics', 'viscous_friction'), float('nan'), r'dynamics\.viscous_friction\[0\] must be finite'),
    (('dynamics', 'yaw_inertia'), 'heavy', r'dynamics\.yaw_inertia must be a number'),
    (('dynamics', 'wheel_inertia'), [1e-3, 1e-3], r'dynamics\.wheel_inertia must be one number or a list of 4'),
    (('dynamics', 'mas'), 1.0, r'dynamics\.mas is not a known key'),
    (('dynamics', 'loop_inertias'), {'mass': 20.0, 'yaw_inertia': 1.0},
     r'dynamics\.loop_inertias\.wheel_inertia is missing'),
    (('dynamics', 'loop_inertias'), {'mass': 0.0, 'yaw_inertia': 1.0, 'wheel_inertia': 0.01},
     r'dynamics\.loop_inertias\.mass must be > 0'),
    (('dynamics', 'loop_inertias'), [20.0, 1.0, 0.01], r'dynamics\.loop_inertias must be a mapping'),
    (('drive', 'gear_ratio'), 0.0, r'drive\.gear_ratio must be > 0'),
    (('firmware', 'loop'), 'analog', r'firmware\.loop must be one of'),
    (('firmware', 'period'), float('inf'), r'firmware\.period must be finite'),
    (('platform', 'wheels'), [], r'platform\.wheels must be a non-empty list'),
    (('drive',), _DELETE, r'drive is missing'),
])
def test_bad_values_are_rejected_naming_the_key(youbot_dict, path, value, match):
    with pytest.raises(ConfigError, match=match):
        parse_profile(_edit(youbot_dict, path, value), source='broken.yaml')


def test_bad_wheels_are_rejected_naming_the_wheel(youbot_dict):
    data = copy.deepcopy(youbot_dict)
    data['platform']['wheels'][2]['radius'] = 0.0
    with pytest.raises(ConfigError, match=r'platform\.wheels\[2\]\.radius must be > 0'):
        parse_profile(data, source='broken.yaml')
    data = copy.deepcopy(youbot_dict)
    data['platform']['wheels'][1]['drive_sign'] = 2
    with pytest.raises(ConfigError, match=r'wheels\[1\].*drive_sign must be \+1 or -1'):
        parse_profile(data, source='broken.yaml')
    data = copy.deepcopy(youbot_dict)
    data['platform']['wheels'] = data['platform']['wheels'][:2]
    with pytest.raises(ConfigError, match='at least 3 wheels'):
        parse_profile(data, source='broken.yaml')


def test_files_that_are_not_profiles(tmp_path):
    broken = tmp_path / 'broken.yaml'
    broken.write_text('name: [unclosed')
    with pytest.raises(ConfigError, match='not valid YAML'):
        load_profile(broken)
    broken.write_text('- just\n- a list\n')
    with pytest.raises(ConfigError, match='must be a mapping'):
        load_profile(broken)
    with pytest.raises(ConfigError, match='unknown profile'):
        load_profile('no_such_robot')
    with pytest.raises(ConfigError, match='does not exist'):
        load_profile(tmp_path / 'missing.yaml')
