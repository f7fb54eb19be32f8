"""Test-only stand-in for the core of ROS 2 `launch` (Jazzy): the parts our launch files use.

Written from the launch documentation and sources (github.com/ros2/launch, branch jazzy) because
neither launch nor launch_ros installs from a package registry here. Semantics kept: launch
arguments are launch configurations set before the description is visited, substitutions are
performed at launch time (never evaluated as code), conditions accept only true/false/1/0,
processes are started in visiting order, process output emits ProcessIO and a process exit
ProcessExited to the registered handlers, a Shutdown event stops every process (SIGINT unless
the shutdown came from a SIGINT, then SIGTERM after `sigterm_timeout`, SIGKILL after
`sigkill_timeout`), and the service returns 1 only when the launch itself failed (an exception in an
action or an event handler: logged as one 'Caught exception in launch' line; a node exiting non-zero
is logged, not returned).
Nothing here is installed or used outside tests/.
"""
from __future__ import annotations

import collections.abc
import os
import queue
import signal
import subprocess
import sys
import threading
import time
from types import SimpleNamespace
from typing import Any
from collections.abc import Callable, Iterable

_PRINT_LOCK = threading.Lock()


def log(level: str, name: str, msg: str) -> None:
    """One launch log line in launch's screen format: [LEVEL] [name]: msg."""
    with _PRINT_LOCK:
        sys.stdout.write(f'[{level}] [{name}]: {msg}\n')
        sys.stdout.flush()


def _screen(line: str) -> None:
    with _PRINT_LOCK:
        sys.stdout.write(line + '\n')
        sys.stdout.flush()


# ---------------------------------------------------------------------------- substitutions
class SubstitutionFailure(RuntimeError):
    """A substitution could not be performed (e.g. an undeclared launch configuration)."""


class Substitution:
    """Something that becomes text at launch time."""

    def perform(self, context: LaunchContext) -> str:
        """The text in `context`."""
        raise NotImplementedError

    def describe(self) -> str:
        """Human-readable form."""
        return repr(self)


class TextSubstitution(Substitution):
    """Literal text."""

    def __init__(self, *, text: str) -> None:
        self.text = text

    def perform(self, context):
        return self.text


def normalize_to_list_of_substitutions(subs: Any) -> list[Substitution]:
    """str | Substitution | iterable of those -> list of Substitution."""
    def _one(x):
        if isinstance(x, Substitution):
            return x
        if isinstance(x, str):
            return TextSubstitution(text=x)
        raise TypeError(f'expected str or Substitution, got {type(x).__name__}: {x!r}')
    if isinstance(subs, (str, Substitution)):
        return [_one(subs)]
    if isinstance(subs, collections.abc.Iterable):
        return [_one(x) for x in subs]
    raise TypeError(f'expected str, Substitution or an iterable of them, got {subs!r}')


def perform_substitutions(context: LaunchContext, subs: Iterable[Substitution]) -> str:
    """Concatenated text of `subs`."""
    return ''.join(context.perform_substitution(s) for s in subs)


# ---------------------------------------------------------------------------- conditions
class InvalidConditionExpressionError(ValueError):
    """A condition expression that is not one of true/false/1/0."""


class Condition:
    """A predicate evaluated when the action it guards is visited."""

    def __init__(self, *, predicate: Callable[[LaunchContext], bool] | None = None) -> None:
        self._predicate = predicate

    def evaluate(self, context: LaunchContext) -> bool:
        """True when the guarded action should run."""
        return bool(self._predicate(context)) if self._predicate else True


def evaluate_condition_expression(context: LaunchContext, expression: list[Substitution]) -> bool:
    """launch's rule: the stripped, lower-cased text must be true/1 or false/0; anything else is an error."""
    text = perform_substitutions(context, expression).strip().lower()
    if text in ('true', '1'):
        return True
    if text in ('false', '0'):
        return False
    raise InvalidConditionExpressionError(
        f"invalid condition expression '{text}': expected one of true, 1, false, 0")


# ---------------------------------------------------------------------------- events
class Event:
    """Base of everything that goes through the event queue."""

    name = 'launch.Event'


class Shutdown(Event):
    """Emitted to shut the launched system down."""

    name = 'launch.events.Shutdown'

    def __init__(self, *, reason: str = 'reason not given', due_to_sigint: bool = False) -> None:
        self.reason = reason
        self.due_to_sigint = due_to_sigint


class ProcessStarted(Event):
    """A process was started."""

    name = 'launch.events.process.ProcessStarted'

    def __init__(self, *, action, name, cmd, pid):
        self.action, self.process_name, self.cmd, self.pid = action, name, cmd, pid


class ProcessExited(Event):
    """A process exited; `returncode` is its exit status (negative: killed by that signal)."""

    name = 'launch.events.process.ProcessExited'

    def __init__(self, *, action, name, cmd, pid, returncode):
        self.action, self.process_name, self.cmd, self.pid = action, name, cmd, pid
        self.returncode = returncode


class ProcessIO(Event):
    """A process wrote to stdout (fd 1) or stderr (fd 2); `text` is the bytes (real launch: any chunk)."""

    name = 'launch.events.process.ProcessIO'

    def __init__(self, *, action, name, cmd, pid, text: bytes, fd: int):
        self.action, self.process_name, self.cmd, self.pid = action, name, cmd, pid
        self.text, self.fd = text, fd
        self.from_stdin, self.from_stdout, self.from_stderr = fd == 0, fd == 1, fd == 2


# ---------------------------------------------------------------------------- entities
class LaunchDescriptionEntity:
    """Anything a LaunchDescription may hold."""

    def visit(self, context: LaunchContext) -> list | None:
        """Run this entity; returns sub-entities to visit next."""
        raise NotImplementedError


class Action(LaunchDescriptionEntity):
    """An action, optionally guarded by a condition."""

    def __init__(self, *, condition: Condition | None = None) -> None:
        self.condition = condition

    def visit(self, context):
        if self.condition is not None and not self.condition.evaluate(context):
            return None
        return self.execute(context)

    def execute(self, context: LaunchContext) -> list | None:
        """Do the work; returns sub-entities or None."""
        return None


class LaunchDescription(LaunchDescriptionEntity):
    """An ordered list of entities."""

    def __init__(self, initial_entities: Iterable[LaunchDescriptionEntity] | None = None) -> None:
        self.entities = list(initial_entities or [])

    def add_action(self, action: LaunchDescriptionEntity) -> None:
        """Append an entity."""
        self.entities.append(action)

    add_entity = add_action

    def visit(self, context):
        return list(self.entities)

    def get_launch_arguments(self) -> list:
        """The DeclareLaunchArgument actions reachable without launching, in order."""
        from .actions import DeclareLaunchArgument, GroupAction
        found = []

        def walk(entities):
            for e in entities:
                if isinstance(e, DeclareLaunchArgument):
                    found.append(e)
                elif isinstance(e, LaunchDescription):
                    walk(e.entities)
                elif isinstance(e, GroupAction):
                    walk(e.actions)
        walk(self.entities)
        return found


class EventHandler:
    """Matches events and returns entities to visit for them."""

    def __init__(self, *, matcher: Callable[[Event], bool],
                 entities: Any = None, handle_once: bool = False) -> None:
        self.matcher = matcher
        self.entities = entities
        self.handle_once = handle_once

    def matches(self, event: Event) -> bool:
        """True when this handler wants `event`."""
        return self.matcher(event)

    def handle(self, event: Event, context: LaunchContext) -> list | None:
        """Entities to visit for `event` (context.locals.event is set)."""
        context.locals.event = event
        ents = self.entities
        if callable(ents):
            ents = ents(event, context)
        if ents is None:
            return None
        if isinstance(ents, LaunchDescriptionEntity):
            return [ents]
        return list(ents)


# ---------------------------------------------------------------------------- context and service
class LaunchContext:
    """Launch configurations, event handlers, the event queue and shutdown state."""

    def __init__(self, argv: list[str] | None = None) -> None:
        self.argv = list(argv or [])
        self.launch_configurations: dict[str, str] = {}
        self.environment = os.environ
        self.locals = SimpleNamespace()
        self._handlers: list[EventHandler] = []
        # SimpleQueue: put() is reentrant, so the SIGINT/SIGTERM handlers (which run on the main thread,
        # possibly inside get()) can queue a Shutdown without deadlocking on a Queue's mutex.
        self._events: queue.SimpleQueue[Event] = queue.SimpleQueue()
        self._is_shutdown = False
        self.processes: list = []          # running ExecuteProcess actions (stand-in bookkeeping)

    @property
    def is_shutdown(self) -> bool:
        """True once a Shutdown event has been handled."""
        return self._is_shutdown

    def register_event_handler(self, handler: EventHandler) -> None:
        """Handlers registered later are consulted first (launch inserts at the front)."""
        self._handlers.insert(0, handler)

    def unregister_event_handler(self, handler: EventHandler) -> None:
        """Forget `handler`."""
        self._handlers.remove(handler)

    def emit_event_sync(self, event: Event) -> None:
        """Queue `event` (thread-safe)."""
        self._events.put(event)

    emit_event = emit_event_sync

    def perform_substitution(self, substitution: Substitution) -> str:
        """Text of one substitution."""
        return substitution.perform(self)


class LaunchService:
    """Visits launch descriptions and runs the event loop until everything has exited."""

    def __init__(self, argv: list[str] | None = None, poll_s: float = 0.05) -> None:
        self.context = LaunchContext(argv)
        self._pending: collections.deque = collections.deque()
        self._shutting_down = False
        self._poll_s = poll_s
        self._sigint_seen = False

    def include_launch_description(self, description: LaunchDescription) -> None:
        """Visit `description` when run() starts."""
        self._pending.append(description)

    # -- signals (installed by run(); the handlers only queue events)
    def _on_sigint(self, signum, frame) -> None:
        if self._sigint_seen:
            log('WARNING', 'launch', 'user interrupted with ctrl-c (SIGINT) again, ignoring...')
            return
        self._sigint_seen = True
        log('WARNING', 'launch', 'user interrupted with ctrl-c (SIGINT)')
        self.context.emit_event(Shutdown(reason='ctrl-c (SIGINT)', due_to_sigint=True))

    def _on_sigterm(self, signum, frame) -> None:
        log('ERROR', 'launch', f'user interrupted with ctrl-\\ ({signal.Signals(signum).name}), terminating...')
        self.context.emit_event(Shutdown(reason='SIGTERM', due_to_sigint=False))

    def _visit(self, entity) -> None:
        stack = [entity]
        while stack:
            ent = stack.pop()
            subs = ent.visit(self.context)
            if subs:
                stack.extend(reversed(list(subs)))

    def _handle(self, event: Event) -> None:
        if isinstance(event, Shutdown):
            if not self._shutting_down:
                self._shutting_down = True
                self.context._is_shutdown = True
                for proc in list(self.context.processes):
                    proc._shutdown(send_sigint=not event.due_to_sigint)
        for handler in list(self.context._handlers):
            if handler.matches(event):
                if handler.handle_once:
                    self.context.unregister_event_handler(handler)
                try:
                    ents = handler.handle(event, self.context)
                    for e in ents or []:
                        self._visit(e)
                finally:
                    self.context.locals.__dict__.pop('event', None)

    def _busy(self) -> bool:
        return bool(self.context.processes) or not self.context._events.empty()

    def run(self) -> int:
        """Run until idle or shut down and every process has exited; 0 unless the launch failed."""
        old_int = signal.signal(signal.SIGINT, self._on_sigint)
        old_term = signal.signal(signal.SIGTERM, self._on_sigterm)
        code = 0
        try:
            try:
                while self._pending:
                    self._visit(self._pending.popleft())
            except Exception as exc:  # noqa: BLE001 - launch reports and shuts down
                log('ERROR', 'launch', f'Caught exception in launch (see debug for traceback): {exc}')
                self.context.emit_event(Shutdown(reason=str(exc)))
                code = 1
            while True:
                try:
                    event = self.context._events.get(timeout=self._poll_s)
                except queue.Empty:
                    event = None
                if event is not None:
                    try:
                        self._handle(event)
                    except Exception as exc:  # noqa: BLE001
                        log('ERROR', 'launch', f'Caught exception in launch (see debug for traceback): {exc}')
                        self.context.emit_event(Shutdown(reason=str(exc)))
                        code = 1
                for proc in list(self.context.processes):
                    proc._tick()
                if not self._busy():
                    if not self._shutting_down:
                        self.context.emit_event(Shutdown(reason='idle'))
                        continue
                    return code
        finally:
            signal.signal(signal.SIGINT, old_int)
            signal.signal(signal.SIGTERM, old_term)


def _process_counter() -> Callable[[str], str]:
    """launch numbers processes with one counter for all of them: sim_node-1, mavlink_bridge_node-2."""
    count = 0
    lock = threading.Lock()

    def name(base: str) -> str:
        nonlocal count
        with lock:
            count += 1
            return f'{base}-{count}'
    return name


unique_process_name = _process_counter()


class ExecuteProcess(Action):
    """Run a command; its output goes to the screen (`output='screen'`) or, stderr only, for 'log'."""

    def __init__(self, *, cmd: Iterable[Any], name: Any = None, cwd: Any = None,
                 env: dict | None = None, additional_env: dict | None = None, output: str = 'log',
                 sigterm_timeout: Any = '5', sigkill_timeout: Any = '5', on_exit: Any = None,
                 shell: bool = False, emulate_tty: bool = False, respawn: bool = False,
                 **kwargs) -> None:
        super().__init__(**kwargs)
        self.cmd = [normalize_to_list_of_substitutions(c) for c in cmd]
        self._name = name
        self._cwd = cwd
        self._env = env
        self._additional_env = additional_env or {}
        self._output = output
        self._sigterm_timeout = sigterm_timeout
        self._sigkill_timeout = sigkill_timeout
        self._on_exit = on_exit
        self._shell = shell
        self.process_name = ''
        self._proc: subprocess.Popen | None = None
        self._context: LaunchContext | None = None
        self._shutdown_at: float | None = None
        self._escalated = ''
        self._threads: list[threading.Thread] = []

    def _text(self, context, value) -> str:
        return perform_substitutions(context, normalize_to_list_of_substitutions(value))

    def _prepare(self, context) -> list[str]:
        """Hook for launch_ros.Node: extends self.cmd before the substitutions are performed."""
        return [perform_substitutions(context, c) for c in self.cmd]

    def execute(self, context):
        self._context = context
        cmd = self._prepare(context)
        base = self._text(context, self._name) if self._name is not None else os.path.basename(cmd[0])
        self.process_name = unique_process_name(base)
        if self._on_exit is not None:
            from .event_handlers import OnProcessExit
            context.register_event_handler(OnProcessExit(target_action=self, on_exit=self._on_exit))
        if context.is_shutdown:
            return None
        env = dict(self._env if self._env is not None else context.environment)
        for k, v in self._additional_env.items():
            env[self._text(context, k)] = self._text(context, v)
        cwd = self._text(context, self._cwd) if self._cwd is not None else None
        output = self._text(context, self._output)
        try:
            self._proc = subprocess.Popen(cmd, cwd=cwd, env=env, stdout=subprocess.PIPE,
                                          stderr=subprocess.PIPE, stdin=subprocess.DEVNULL)
        except OSError as exc:
            log('ERROR', self.process_name, f'exception occurred while executing process: {exc}')
            return None
        self._cmd_text = ' '.join(cmd)
        log('INFO', self.process_name, f'process started with pid [{self._proc.pid}]')
        context.processes.append(self)
        for fd, stream, to_screen in ((1, self._proc.stdout, output in ('screen', 'both')),
                                      (2, self._proc.stderr, output in ('screen', 'both', 'log'))):
            t = threading.Thread(target=self._pump, args=(stream, to_screen, fd, cmd), daemon=True)
            t.start()
            self._threads.append(t)
        threading.Thread(target=self._wait, daemon=True).start()
        context.emit_event(ProcessStarted(action=self, name=self.process_name, cmd=cmd, pid=self._proc.pid))
        return None

    def _pump(self, stream, to_screen: bool, fd: int, cmd: list[str]) -> None:
        for raw in iter(stream.readline, b''):
            self._context.emit_event(ProcessIO(action=self, name=self.process_name, cmd=cmd,
                                               pid=self._proc.pid, text=raw, fd=fd))
            if to_screen:
                _screen(f'[{self.process_name}] ' + raw.decode('utf-8', 'replace').rstrip('\n'))
        stream.close()

    def _wait(self) -> None:
        code = self._proc.wait()
        for t in self._threads:
            t.join(timeout=5.0)
        if code == 0:
            log('INFO', self.process_name, f'process has finished cleanly [pid {self._proc.pid}]')
        else:
            log('ERROR', self.process_name,
                f"process has died [pid {self._proc.pid}, exit code {code}, cmd '{self._cmd_text}'].")
        ctx = self._context
        ctx.emit_event(ProcessExited(action=self, name=self.process_name, cmd=self._cmd_text,
                                     pid=self._proc.pid, returncode=code))
        if self in ctx.processes:
            ctx.processes.remove(self)

    def _shutdown(self, *, send_sigint: bool) -> None:
        if self._proc is None or self._proc.poll() is not None or self._shutdown_at is not None:
            return
        self._shutdown_at = time.monotonic()
        if send_sigint:
            log('INFO', self.process_name, f"sending signal 'SIGINT' to process[{self.process_name}]")
            self._signal(signal.SIGINT)

    def _signal(self, sig) -> None:
        try:
            self._proc.send_signal(sig)
        except ProcessLookupError:
            pass

    def _tick(self) -> None:
        """Escalate a shutdown: SIGTERM after sigterm_timeout, SIGKILL after sigkill_timeout more."""
        if self._shutdown_at is None or self._proc.poll() is not None:
            return
        ctx = self._context
        term = float(self._text(ctx, self._sigterm_timeout))
        kill = float(self._text(ctx, self._sigkill_timeout))
        waited = time.monotonic() - self._shutdown_at
        if waited > term and not self._escalated:
            self._escalated = 'SIGTERM'
            log('WARNING', self.process_name, f"process[{self.process_name}] failed to terminate '{term}' "
                "seconds after receiving 'SIGINT', escalating to 'SIGTERM'")
            self._signal(signal.SIGTERM)
        elif waited > term + kill and self._escalated == 'SIGTERM':
            self._escalated = 'SIGKILL'
            log('ERROR', self.process_name, f"process[{self.process_name}] failed to terminate '{kill}' "
                "seconds after receiving 'SIGTERM', escalating to 'SIGKILL'")
            self._signal(signal.SIGKILL)
