"""Shared fixtures of the assist_policy tests."""
import pytest

from assist_sim.core.world import LandingWorld


@pytest.fixture(scope='module')
def depth_at(request):
    """depth_at(x, y, z): the depth frame rendered from there in the test module's SCENE (cached per module)."""
    world = LandingWorld()
    world.reset(scene=request.module.SCENE)
    cache = {}

    def render(x, y, z):
        if (x, y, z) not in cache:
            cache[(x, y, z)] = world.render_from([x, y, z]).depth.copy()
        return cache[(x, y, z)]
    yield render
    world.close()
