"""Suite-wide fixtures (every test folder in pytest.ini's testpaths)."""
from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _python_logging_released():
    """After each test, Python logging no longer forwards to a node an in-process test built (ros_common)."""
    yield
    from assist_common.ros_common import release_logging
    release_logging()


@pytest.fixture(scope='module')
def depth_at(request):
    """depth_at(x, y, z): the depth frame rendered from there in the test module's SCENE (cached per module)."""
    from assist_sim.core.world import LandingWorld
    world = LandingWorld()
    world.reset(scene=request.module.SCENE)
    cache = {}

    def render(x, y, z):
        if (x, y, z) not in cache:
            cache[(x, y, z)] = world.render_from([x, y, z]).depth.copy()
        return cache[(x, y, z)]
    yield render
    world.close()


@pytest.fixture(scope='module')
def local_ray():
    """A local Ray instance shared by a module's tests of the --ray paths (it takes ~10 s to start; shut down
    after the module, so its processes do not run beside later tests); the ray module. Skipped where ray is
    not installed (requirements.txt installs it, so `make test` runs these)."""
    ray = pytest.importorskip('ray', reason='ray is in requirements.txt; this runs wherever make test installed it')
    from assist_lab.cluster import connect_ray
    connect_ray('auto')
    yield ray
    ray.shutdown()
