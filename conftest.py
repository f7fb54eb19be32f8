"""Suite-wide fixtures (every test folder in pytest.ini's testpaths)."""
from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _python_logging_released():
    """After each test, Python logging no longer forwards to a node an in-process test built (ros_common)."""
    yield
    from assist_common.ros_common import release_logging
    release_logging()
