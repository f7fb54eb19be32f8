"""launch.events stand-in."""
from . import process  # noqa: F401
from .._impl import Event, Shutdown  # noqa: F401
