"""launch.events.process stand-in."""
from .._impl import ProcessExited, ProcessIO, ProcessStarted  # noqa: F401
