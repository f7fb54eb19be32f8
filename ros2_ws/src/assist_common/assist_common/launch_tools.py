"""Helpers for the workspace's launch files (imported only by launch files: needs ROS 2 `launch`)."""
from __future__ import annotations

from launch.actions import EmitEvent, LogInfo, RegisterEventHandler
from launch.event_handlers import OnProcessExit
from launch.events import Shutdown

BOOL_CHOICES = ['true', 'false']


def shutdown_when_exits(node, what: str) -> RegisterEventHandler:
    """When `node`'s process exits while the launch is running, log why and shut the whole launch down.

    `what` says what the node is needed for. Exits during a shutdown (Ctrl-C, another node's
    death) are not reported again.
    """
    def on_exit(event, context):
        if context.is_shutdown:
            return None
        reason = (f'{event.process_name} exited with code {event.returncode}; {what}: '
                  'shutting the launch down')
        return [LogInfo(msg=reason), EmitEvent(event=Shutdown(reason=reason))]
    return RegisterEventHandler(OnProcessExit(target_action=node, on_exit=on_exit))
