"""Suite-wide fixtures (every test folder in pytest.ini's testpaths)."""
from __future__ import annotations

import os
import tempfile

import pytest


def pytest_configure(config):
    """The suite's cache (exported encoders, generated textures: assist_common.cache) is in the temporary folder,
    not the user's home (every process the tests start, graph nodes included, inherits ASSIST_CACHE_DIR).

    Under pytest-xdist each worker gets its own DDS domains: ROS_DOMAIN_ID (the default graph of tests that take
    it from the environment) and a disjoint slice of the private domains (assist_common.domains), so two workers'
    graphs never meet."""
    os.environ.setdefault('ASSIST_CACHE_DIR', os.path.join(tempfile.gettempdir(), f'assist-test-cache-{os.getuid()}'))
    worker = os.environ.get('PYTEST_XDIST_WORKER')
    if worker:
        from assist_common.domains import DOMAIN_IDS_ENV, split_range
        n, count = int(worker.removeprefix('gw')), int(os.environ.get('PYTEST_XDIST_WORKER_COUNT', '1'))
        os.environ[DOMAIN_IDS_ENV] = split_range(n, count)
        os.environ['ROS_DOMAIN_ID'] = str(40 + n)


def pytest_collection_modifyitems(config, items):
    """Files holding a test marked slow run first, the longest first (the marker's `seconds`, else 60), so that on
    parallel workers (make test: --dist loadfile --no-loadscope-reorder keeps this order) the long ones do not end
    the run alone; the order within a file is kept."""
    seconds: dict = {}
    for item in items:
        marker = item.get_closest_marker('slow')
        if marker:
            seconds[item.path] = max(seconds.get(item.path, 0), marker.kwargs.get('seconds', 60))
    items.sort(key=lambda item: -seconds.get(item.path, 0))


@pytest.fixture(autouse=True)
def _python_logging_released():
    """After each test, Python logging no longer forwards to a node an in-process test built (forward_logging)."""
    yield
    from assist_common.ros_io import release_logging
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
