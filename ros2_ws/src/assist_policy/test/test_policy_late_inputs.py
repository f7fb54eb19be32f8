"""Late inputs: a pilot link that delivers every command late (a starved CPU) still flies the pilot."""
import importlib.util
from pathlib import Path

import numpy as np
import pytest

from assist_policy.policy_core import InputRejected, PolicyCore, PolicyCoreConfig

_spec = importlib.util.spec_from_file_location('policy_core_helpers', Path(__file__).with_name('test_policy_core.py'))
_helpers = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_helpers)
constant_actor = _helpers.constant_actor


@pytest.fixture
def core(tmp_path):
    return PolicyCore(constant_actor(tmp_path / 'a.pt', [0.0, 0.0, 0.0]), PolicyCoreConfig(mode='latent'))


def test_commands_arriving_late_are_flown_and_counted(core):
    # every command arrives 0.8 s after its stamp (> pilot_timeout_s 0.5 s), one every 0.05 s
    for k in range(40):
        t = 10.0 + 0.05 * k
        core.set_odom(t, [1, 0, 2], [0, 0, 0])
        core.set_pilot(t, [0.3, 0.0, -0.4], stamp=t - 0.8)
        out = core.step(t + 0.01)
        # no latent: the assistant relinquishes and the pilot's late command is what flies (V = u)
        np.testing.assert_allclose(out.velocity, [0.3, 0.0, -0.4])
    assert core.late_pilot == 40
    assert core.pilot_latency_s == pytest.approx(0.8)


def test_pilot_absent_once_commands_stop_arriving(core):
    core.set_odom(10.0, [1, 0, 2], [0, 0, 0])
    core.set_pilot(10.0, [0.3, 0.0, 0.0], stamp=9.2)
    core.set_odom(10.6, [1, 0, 2], [0, 0, 0])
    # 0.6 s after the last arrival (> pilot_timeout_s): no pilot, u = 0
    np.testing.assert_allclose(core.step(10.6).velocity, np.zeros(3))


def test_commands_older_than_max_latency_are_rejected(core):
    with pytest.raises(InputRejected) as err:
        core.set_pilot(10.0, [0.3, 0.0, 0.0], stamp=10.0 - 2.5)
    assert err.value.reason == 'pilot_stale_stamp'
    assert core.rejections['pilot_stale_stamp'] == 1
    assert core.pilot_command(10.0).tolist() == [0.0, 0.0, 0.0]


def test_an_older_command_never_replaces_a_newer_one(core):
    core.set_pilot(10.0, [0.3, 0.0, 0.0], stamp=9.9)
    with pytest.raises(InputRejected) as err:
        core.set_pilot(10.05, [-0.3, 0.0, 0.0], stamp=9.5)      # another publisher's older command
    assert err.value.reason == 'pilot_out_of_order'
    assert core.pilot_command(10.06).tolist() == [0.3, 0.0, 0.0]
    # once the held command has timed out, a restarted publisher's clock may start earlier
    core.set_pilot(11.0, [0.0, 0.2, 0.0], stamp=9.6)
    assert core.pilot_command(11.0).tolist() == [0.0, 0.2, 0.0]


def test_max_latency_is_range_checked():
    with pytest.raises(ValueError, match='pilot_max_latency_s'):
        PolicyCoreConfig(pilot_max_latency_s=0.0)
