"""launch.event_handlers stand-in: OnProcessExit, OnProcessIO, OnProcessStart, OnShutdown."""
from ._impl import EventHandler, ProcessExited, ProcessIO, ProcessStarted, Shutdown


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


class OnProcessIO(EventHandler):
    """Handles ProcessIO of `target_action`: on_stdout / on_stderr / on_stdin are f(event) -> entities or None."""

    def __init__(self, *, target_action=None, on_stdin=None, on_stdout=None, on_stderr=None, **kwargs) -> None:
        def handle(event, context):
            for wanted, callback in ((event.from_stdout, on_stdout), (event.from_stderr, on_stderr),
                                     (event.from_stdin, on_stdin)):
                if wanted:
                    return callback(event) if callback is not None else None
            return None
        super().__init__(matcher=_action_matcher(target_action, ProcessIO), entities=handle, **kwargs)
