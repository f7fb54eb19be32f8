"""Helpers for the workspace's launch files (imported only by launch files: needs ROS 2 `launch`)."""
from __future__ import annotations

import re

from launch.actions import EmitEvent, LogInfo, RegisterEventHandler
from launch.event_handlers import OnProcessExit, OnProcessIO
from launch.events import Shutdown

BOOL_CHOICES = ['true', 'false']

# A line a node prints when something is really wrong: run_node's start-up error ("error: ..."), an
# rclpy log line at ERROR/FATAL, or the last line of a Python traceback ("ValueError: ...").
_ERROR_LINE = re.compile(r'^(error: |\[(ERROR|FATAL)\] |[A-Za-z_][\w.]*(Error|Exception): )')
_MAX_REASON_CHARS = 400


class RequiredNodeFailed(RuntimeError):
    """A node the launch cannot run without exited non-zero: `ros2 launch` reports this one line, exits 1."""


def first_error_line(text: str) -> str | None:
    """The first line of `text` that reports an error (see _ERROR_LINE), stripped; None when there is none."""
    for line in text.splitlines():
        line = line.strip()
        if _ERROR_LINE.match(line):
            return line
    return None


class _FirstError:
    """Remembers the first error line a process printed (its output arrives in chunks, lines may split)."""

    def __init__(self) -> None:
        self.line: str | None = None
        self._partial = ''

    def feed(self, event) -> None:
        """OnProcessIO callback: scan complete lines until the first error line is found."""
        if self.line is not None:
            return None
        text = self._partial + event.text.decode('utf-8', 'replace')
        complete, _, self._partial = text.rpartition('\n')
        self._partial = self._partial[-_MAX_REASON_CHARS:]
        self.line = first_error_line(complete)
        return None


def shutdown_when_exits(node, what: str) -> list:
    """When `node`'s process exits while the launch is running, shut the whole launch down, saying why.

    `what` says what the node is needed for. A non-zero exit is a failure: it is raised as
    RequiredNodeFailed, which `ros2 launch` prints as one error line (the node, its exit code, the
    first error the node printed, `what`) and turns into exit code 1 after stopping the other nodes.
    A clean exit (0) is logged and shuts the launch down normally. Exits during a shutdown (Ctrl-C,
    another node's failure) are not reported again. Returns the event handlers to add to the
    LaunchDescription.
    """
    first = _FirstError()

    def on_exit(event, context):
        if context.is_shutdown:
            return None
        if event.returncode != 0:
            told = f': {first.line[:_MAX_REASON_CHARS]}' if first.line else ''
            raise RequiredNodeFailed(f'{event.process_name} exited with code {event.returncode}{told}; '
                                     f'{what}: shutting the launch down')
        reason = f'{event.process_name} exited; {what}: shutting the launch down'
        return [LogInfo(msg=reason), EmitEvent(event=Shutdown(reason=reason))]
    return [RegisterEventHandler(OnProcessIO(target_action=node, on_stdout=first.feed, on_stderr=first.feed)),
            RegisterEventHandler(OnProcessExit(target_action=node, on_exit=on_exit))]
