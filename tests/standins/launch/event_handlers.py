"""launch.event_handlers stand-in: OnProcessExit, OnProcessStart, OnShutdown."""
from ._impl import EventHandler, ProcessExited, ProcessStarted, Shutdown


def _action_matcher(target_action, cls):
    def match(event):
        if not isinstance(event, cls):
            return False
        if target_action is None:
            return True
        if callable(target_action) and not hasattr(target_action, 'visit'):
            return bool(target_action(event.action))
        return event.action is target_action
    return match


class OnProcessExit(EventHandler):
    """Handles ProcessExited of `target_action` (any process when None); `on_exit` is entities or f(event, context)."""

    def __init__(self, *, target_action=None, on_exit, **kwargs) -> None:
        super().__init__(matcher=_action_matcher(target_action, ProcessExited), entities=on_exit, **kwargs)


class OnProcessStart(EventHandler):
    """Handles ProcessStarted of `target_action` (any process when None)."""

    def __init__(self, *, target_action=None, on_start, **kwargs) -> None:
        super().__init__(matcher=_action_matcher(target_action, ProcessStarted), entities=on_start, **kwargs)


class OnShutdown(EventHandler):
    """Handles the Shutdown event."""

    def __init__(self, *, on_shutdown, **kwargs) -> None:
        super().__init__(matcher=lambda e: isinstance(e, Shutdown), entities=on_shutdown, **kwargs)
