"""launch.events.process stand-in."""
from .._impl import ProcessExited, ProcessStarted  # noqa: F401
