"""policy_node in a real graph (subprocess, private domain): blending, stale inputs, NaN handling."""
import math
import threading
import time

import numpy as np
import pytest

from assist_policy.testing import LATENT, constant_actor

pytestmark = pytest.mark.graph

LATENT = LATENT


def test_policy_node_blends_relinquishes_when_stale_and_rejects_nan(probe, start_node, wait, tmp_path):
    model = constant_actor(tmp_path / 'actor.pt', [0.8, 0.0, 0.0])
    # the probe's pilot holds a key: the pilot override (tested in test_policy_floor_guard_graph) is off here
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 20.0,
                                      'pilot_override': False})
    assert wait(lambda: len(probe.since(probe.cmd, 0)) > 0 or node.proc.poll() is not None, 30), node.log()
    assert node.proc.poll() is None, node.log()
    # all inputs fresh: agent a = (0.8, 0, 0), V = (u + a) / 2 (publish until discovery is done)
    t0 = time.monotonic()
    while not probe.since(probe.agent, t0) and time.monotonic() - t0 < 30:
        probe.run(0.2)
    t0 = probe.run(1.5)
    cmds, agents = probe.since(probe.cmd, t0 + 0.5), probe.since(probe.agent, t0 + 0.5)
    assert len(cmds) > 5 and len(agents) > 5, node.log()
    np.testing.assert_allclose(agents[-1], [0.8, 0, 0], atol=1e-5)
    np.testing.assert_allclose(cmds[-1], [0.4, 0.5, 0], atol=1e-5)
    # latent stops: after its 0.5 s timeout the policy relinquishes (V = u) and stops publishing a
    t1 = probe.run(3.0, latent=False)
    late = probe.since(probe.cmd, t1 + 1.5)
    assert late and all(np.allclose(v, [0, 1, 0], atol=1e-6) for v in late)
    assert not probe.since(probe.agent, t1 + 1.5)
    # NaN latent is rejected (counts as absent); NaN pilot is rejected (u = 0 once stale)
    t2 = probe.run(3.0, latent_value=math.nan)
    late = probe.since(probe.cmd, t2 + 1.5)
    assert late and all(np.all(np.isfinite(v)) and np.allclose(v, [0, 1, 0], atol=1e-6) for v in late)
    t3 = probe.run(3.0, u=(math.nan, 0.0, 0.0))
    late = probe.since(probe.cmd, t3 + 1.5)
    # pilot absent (u = 0), latent fresh: V = (0 + a) / 2
    assert late and all(np.allclose(v, [0.4, 0, 0], atol=1e-5) for v in late)
    assert 'rejected latent' in node.log() and 'rejected pilot' in node.log()


def test_policy_node_missing_model_exits_with_one_line(start_node, wait, tmp_path):
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(tmp_path / 'nope.pt')})
    assert wait(lambda: node.proc.poll() is not None, 30)
    assert node.proc.returncode == 1
    assert 'actor file not found' in node.log() and 'Traceback' not in node.log()


def _params(ros, node_name, names):
    """The values of `names` (bools) of the node `node_name` over its get_parameters service.

    A request sent as soon as the service is discovered can be lost while the reply path is still being
    matched (Fast DDS drops a request that arrives before the server's reply writer knows the client): the
    request is sent again, up to three times, rather than waiting on a reply that will not come."""
    from rcl_interfaces.srv import GetParameters
    cli = ros.create_client(GetParameters, f'/{node_name}/get_parameters')
    try:
        assert cli.wait_for_service(timeout_sec=30)
        for _ in range(3):
            done = threading.Event()
            fut = cli.call_async(GetParameters.Request(names=list(names)))
            fut.add_done_callback(lambda f, d=done: d.set())
            if done.wait(10):
                return dict(zip(names, (v.bool_value for v in fut.result().values)))
            cli.remove_pending_request(fut)
        raise AssertionError(f'/{node_name}/get_parameters: no answer to three requests in 30 s')
    finally:
        ros.destroy_client(cli)


def test_goal_agnostic_rules_default_off_in_oracle_mode_only(ros, start_node, tmp_path):
    """Mode oracle knows the goal: its pilot override, pad recall and damper default off (settable); latent: on.

    Each start gets its own node name: a service of a node just stopped can linger in the graph and swallow a
    request meant for its successor of the same name."""
    names = ('floor_guard', 'pilot_override', 'pad_recall', 'oscillation_damper')
    oracle = constant_actor(tmp_path / 'oracle.pt', [0.0, 0.0, 0.0], condition='oracle', latent_dim=0)
    node = start_node('policy_node', {'mode': 'oracle', 'model_path': str(oracle)}, {'__node': 'policy_oracle'})
    assert _params(ros, 'policy_oracle', names) == {'floor_guard': True, 'pilot_override': False,
                                                    'pad_recall': False, 'oscillation_damper': False}, node.log()
    node.stop()
    node = start_node('policy_node', {'mode': 'oracle', 'model_path': str(oracle), 'pilot_override': True},
                      {'__node': 'policy_oracle_set'})
    assert _params(ros, 'policy_oracle_set', names)['pilot_override'] is True, node.log()
    node.stop()
    latent = constant_actor(tmp_path / 'latent.pt', [0.0, 0.0, 0.0])
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(latent)}, {'__node': 'policy_latent'})
    assert _params(ros, 'policy_latent', names) == dict.fromkeys(names, True), node.log()
