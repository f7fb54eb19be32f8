"""policy_node steps on each new latent (camera-to-command latency of one inference), not only on its timer."""
import time

import pytest

from assist_policy.testing import constant_actor

pytestmark = pytest.mark.graph


@pytest.mark.parametrize('step_on_latent', [True, False])
def test_commands_follow_latents_not_the_timer(probe, start_node, wait, tmp_path, step_on_latent):
    model = constant_actor(tmp_path / 'actor.pt', [0.8, 0.0, 0.0])
    # a 1 Hz timer: 20 Hz of commands can only come from stepping on each latent
    node = start_node('policy_node', {'mode': 'latent', 'model_path': str(model), 'rate_hz': 1.0,
                                      'step_on_latent': step_on_latent})
    t0 = time.monotonic()
    while not probe.since(probe.agent, t0) and time.monotonic() - t0 < 30 and node.proc.poll() is None:
        probe.run(0.3)
    assert probe.since(probe.agent, t0), node.log()
    t1 = probe.run(3.0)                                  # inputs at 20 Hz for 3 s
    n = len(probe.since(probe.cmd, t1 + 0.5))
    if step_on_latent:
        assert n >= 25, (n, node.log())                  # ~50 latents in 2.5 s; best effort may drop some
    else:
        assert n <= 4, n                                 # the 1 Hz timer alone
