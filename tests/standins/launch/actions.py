"""launch.actions stand-in: the actions our launch files use."""
from __future__ import annotations

from ._impl import (Action, EventHandler, ExecuteProcess, ProcessExited, Shutdown as ShutdownEvent,  # noqa: F401
                    log, normalize_to_list_of_substitutions, perform_substitutions)


class DeclareLaunchArgument(Action):
    """Declares a launch argument: sets its default when not given, checks `choices`."""

    def __init__(self, name: str, *, default_value=None, description: str | None = None,
                 choices: list[str] | None = None, **kwargs) -> None:
        super().__init__(**kwargs)
        self.name = name
        self.default_value = None if default_value is None else normalize_to_list_of_substitutions(default_value)
        if choices is not None:
            if not choices:
                raise RuntimeError('Provided choices arg is empty. Use None to ignore the choice list.')
            if isinstance(default_value, str) and default_value not in choices:
                raise RuntimeError(f'Provided default_value "{default_value}" is not in provided choices "{choices}".')
        if description is None:
            self.description = 'no description given' if choices is None else 'One of: ' + str(choices)
        else:
            self.description = description
            if choices is not None:
                if not self.description.endswith('.'):
                    self.description += '.'
                self.description += ' Valid choices are: ' + str(choices)
        self.choices = choices

    def execute(self, context):
        if self.name not in context.launch_configurations:
            if self.default_value is None:
                log('ERROR', 'launch.actions.declare_launch_argument',
                    f'Required launch argument "{self.name}" (description: "{self.description}") was not provided')
                raise RuntimeError(f'Required launch argument "{self.name}" was not provided.')
            context.launch_configurations[self.name] = perform_substitutions(context, self.default_value)
        if self.choices is not None:
            value = context.launch_configurations[self.name]
            if value not in self.choices:
                msg = (f'Argument "{self.name}" provided value "{value}" is not valid. '
                       f'Valid options are: {self.choices}')
                log('ERROR', 'launch.actions.declare_launch_argument', msg)
                raise RuntimeError(msg)
        return None


class SetLaunchConfiguration(Action):
    """Sets a launch configuration."""

    def __init__(self, name, value, **kwargs) -> None:
        super().__init__(**kwargs)
        self.name = normalize_to_list_of_substitutions(name)
        self.value = normalize_to_list_of_substitutions(value)

    def execute(self, context):
        context.launch_configurations[perform_substitutions(context, self.name)] = \
            perform_substitutions(context, self.value)
        return None


class RegisterEventHandler(Action):
    """Registers an event handler."""

    def __init__(self, event_handler: EventHandler, **kwargs) -> None:
        super().__init__(**kwargs)
        self.event_handler = event_handler

    def execute(self, context):
        context.register_event_handler(self.event_handler)
        return None


class EmitEvent(Action):
    """Emits an event."""

    def __init__(self, *, event, **kwargs) -> None:
        super().__init__(**kwargs)
        self.event = event

    def execute(self, context):
        context.emit_event(self.event)
        return None


class Shutdown(EmitEvent):
    """Shuts the launched system down; says which process was required when run for a ProcessExited."""

    def __init__(self, *, reason: str = 'reason not given', **kwargs) -> None:
        super().__init__(event=ShutdownEvent(reason=reason), **kwargs)

    def execute(self, context):
        event = getattr(context.locals, 'event', None)
        if isinstance(event, ProcessExited):
            log('INFO', 'launch', f'process[{event.process_name}] was required: shutting down launched system')
        return super().execute(context)


class LogInfo(Action):
    """Logs a message at INFO on the `launch.user` logger."""

    def __init__(self, *, msg, **kwargs) -> None:
        super().__init__(**kwargs)
        self.msg = normalize_to_list_of_substitutions(msg)

    def execute(self, context):
        log('INFO', 'launch.user', perform_substitutions(context, self.msg))
        return None


class GroupAction(Action):
    """Visits its actions (scoping of configurations is not modelled)."""

    def __init__(self, actions, *, scoped: bool = True, forwarding: bool = True, launch_configurations=None,
                 **kwargs) -> None:
        super().__init__(**kwargs)
        self.actions = list(actions)

    def execute(self, context):
        return list(self.actions)


class OpaqueFunction(Action):
    """Calls function(context, *args, **kwargs) at launch time; visits the entities it returns."""

    def __init__(self, *, function, args=None, kwargs=None, **left) -> None:
        super().__init__(**left)
        self.function, self.args, self.kwargs = function, list(args or []), dict(kwargs or {})

    def execute(self, context):
        return self.function(context, *self.args, **self.kwargs)
