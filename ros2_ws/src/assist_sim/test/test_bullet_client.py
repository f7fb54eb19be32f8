"""A pybullet client whose construction was interrupted (Ctrl-C while sim_node starts) is destroyed quietly."""
import gc
import sys

import pytest
from pybullet_utils import bullet_client

from assist_sim.core.world import BulletClient


def test_half_built_client_is_destroyed_without_a_traceback(monkeypatch):
    unraisable = []
    monkeypatch.setattr(sys, 'unraisablehook', unraisable.append)
    half = BulletClient.__new__(BulletClient)      # __init__ interrupted before pybullet.connect returned
    half.__del__()
    with pytest.raises(AttributeError):            # what pybullet_utils' own client does
        bullet_client.BulletClient.__del__(BulletClient.__new__(BulletClient))
    del half
    gc.collect()
    assert unraisable == []
    whole = BulletClient()                          # a finished one still disconnects
    assert whole._client >= 0
    whole.__del__()
    assert whole._client == -1
