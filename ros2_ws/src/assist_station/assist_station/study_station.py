"""The pilot station's user-study driver: runs the protocol of assist_station.study through the graph (rclpy).

The page sends study steps (begin with a participant ID, consent, start a landing, stop practising,
SUS and survey answers); this class turns them into graph actions and files:

* a landing starts by setting sim_node's ``scene_seed`` and ``goal_index`` (and ``auto_reset`` false,
  so the station decides when each landing starts) and policy_node's ``assist_enabled`` (the block's
  condition: on for assisted and assisted_cues) over their parameter services, switching the station's
  own cues (its parameters ``cue_goal``, ``cue_descent``, ``cue_push``) on for an assisted_cues landing and
  off for the others, opening the landing's bag (an in-process bag_record) and calling ``/sim/reset``; the
  vehicle flies the pilot's keys only while a landing is in flight;
* while it flies, the driver measures it: the path flown (the sum of the steps between successive /odom
  positions in stamp order: a message stamped no later than the last is skipped, a step longer than JUMP_M
  faster than MAX_SPEED_MPS between the stamps is a teleport, a reset, not flown, and messages the station
  missed leave a straight step between the ones it got) and the pilot's key presses and corrective presses
  (study.KeyCounter, fed by the station's key state through CountingKeyState);
* the landing ends with the ``/sim/landing`` result of that episode: the row (with the measures) goes to
  landings.csv, the cues go off, the bag is closed, practice landings get feedback (where the drone ended
  relative to the goal pad), block landings none;
* a landing whose page goes away, or that gets no result within ``landing_timeout_s``, is not
  recorded and is flown again (logged in protocol.log).

Between landings, and from the moment the driver starts, the station's cues are off: a study shows them in
its assisted_cues landings only.

Every ROS call is asynchronous (futures with callbacks) on the node's executor; page steps arrive on
the web server's thread and are queued for the node's timer.
"""
from __future__ import annotations

import math
import queue
import re
import threading
import time
from pathlib import Path
from typing import Any
from collections.abc import Callable

import numpy as np
from rcl_interfaces.srv import GetParameters, SetParameters
from rclpy.node import Node
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

from assist_common.frames import heading, rotate_xy

from .station_core import CUES, KeyState, StationConfig, StudyMessage, landing_feedback
from .study import (PRACTICE_BLOCK, KeyCounter, LandingSpec, StudyConfig, StudyError, StudySession,
                    check_participant_id, practice_feedback)

EPISODE_RE = re.compile(r'^episode (\d+): goal pad (\d+)')
SERVICE_WAIT_S = 10.0          # a node's parameter service / /sim/reset not answering this long: sent again or failed
# a landing's graph (sim_node, policy_node for an assisted one) not up this long after the landing began: the step
# fails; nodes that load torch and their models on a busy machine take tens of seconds to start
GRAPH_WAIT_S = 60.0
SERVICE_RETRIES = 2            # a parameter request (idempotent) is sent again this many times before the step fails
BAG_WARMUP_S = 0.6             # the landing's bag subscribes before the episode starts
BAG_TAIL_S = 0.5               # ... and keeps recording this long after the result
INBOX_SIZE = 64                # page steps waiting for the node's timer at most (more are dropped)
WARNING_PERIOD_S = 5.0         # the same refusal is logged at most once per this long (the rest counted)
JUMP_M = 1.0                   # an /odom step longer than this, faster than MAX_SPEED_MPS, is a teleport (a reset)
MAX_SPEED_MPS = 20.0           # ... far above what the vehicle flies (keys 1 m/s, the assistant's push adds little)
CUE_PARAMETERS = tuple(f'cue_{name}' for name in CUES)     # the station's cue switches (pilot_station parameters)


def _same_file(a: str, b: str) -> bool:
    """Whether two model paths name the same file ('' = the shipped model)."""
    if not a or not b:
        return a == b
    return Path(a).expanduser().resolve() == Path(b).expanduser().resolve()


class _Warnings:
    """At most one log line per key per `period_s` (thread-safe); a line says how many were held back."""

    def __init__(self, period_s: float):
        self.period_s = period_s
        self._last: dict[str, float] = {}
        self._held: dict[str, int] = {}
        self._lock = threading.Lock()

    def __call__(self, key: str) -> int | None:
        """None: hold this line back; else log it, with this many held back since the last one."""
        now = time.monotonic()
        with self._lock:
            if now - self._last.get(key, -math.inf) < self.period_s:
                self._held[key] = self._held.get(key, 0) + 1
                return None
            self._last[key] = now
            return self._held.pop(key, 0)


class CountingKeyState(KeyState):
    """The station's key state that also hands every change of the pilot's held keys to a KeyCounter."""

    def __init__(self, cfg: StationConfig | None = None, counter: KeyCounter | None = None):
        super().__init__(cfg)
        self.counter = counter or KeyCounter()

    def set(self, down: Any, now: float) -> np.ndarray:
        """Replace the held set (KeyState.set); keys that timed out before it count as released first."""
        self.counter.note(self.held(now))
        v = super().set(down, now)
        self.counter.note(self.held(now))
        return v

    def release_all(self) -> None:
        """Every key up (KeyState.release_all)."""
        super().release_all()
        self.counter.note(())


class _Call:
    """One pending service call: its future, deadline and what to do with the answer.

    `again` (idempotent requests only: setting or reading parameters) sends the same request anew: a call not
    answered within its time is sent again up to SERVICE_RETRIES times before the step fails (a loaded machine
    can hold a parameter service's answer back for seconds). The answer to any of the tries counts: a node
    whose queue runs longer than `timeout_s` answers the first request after the second was sent.
    """

    def __init__(self, what: str, future: Any, on_done: Callable[[Any], None], timeout_s: float = SERVICE_WAIT_S,
                 again: Callable[[], Any] | None = None):
        self.what, self.on_done, self.again = what, on_done, again
        self.futures = [future]
        self.timeout_s = timeout_s
        self.deadline = time.monotonic() + timeout_s

    @property
    def tries(self) -> int:
        """How many times the request has been sent."""
        return len(self.futures)

    @property
    def future(self) -> Any:
        """The first try's future that is done (the latest try's while none is)."""
        return next((f for f in self.futures if f.done()), self.futures[-1])

    def retry(self) -> bool:
        """Send the request again (one more future, a fresh deadline); False when it may not or has been sent
        enough."""
        if self.again is None or self.tries > SERVICE_RETRIES:
            return False
        self.futures.append(self.again())
        self.deadline = time.monotonic() + self.timeout_s
        return True


class StudyDriver:
    """Protocol + graph actions for one station (one participant at a time)."""

    def __init__(self, node: Node, cfg: StudyConfig, config_text: str, root: Path, publish_view: Callable[[dict], None],
                 push_event: Callable[[dict], None], sim_node: str = '/sim_node', policy_node: str = '/policy_node',
                 encoder_node: str = '/encoder_node', key_counter: KeyCounter | None = None):
        """`node` hosts the study (the pilot station: its cue parameters are switched per landing, a node without
        them has no cues to switch); `key_counter` is fed the pilot's keys (None: key presses not measured)."""
        self.node, self.cfg, self.text, self.root = node, cfg, config_text, Path(root)
        self.keys = key_counter
        self.root.mkdir(parents=True, exist_ok=True)
        self._publish_view, self._push_event = publish_view, push_event
        self.session: StudySession | None = None
        self.inbox: queue.Queue[StudyMessage | tuple[str, Any]] = queue.Queue(maxsize=INBOX_SIZE)
        self._warnings = _Warnings(WARNING_PERIOD_S)
        self._begin_lock = threading.Lock()
        self._begin_pending = False      # a begin waits in the inbox: more begins are refused until it is handled
        self._begin_duplicates = 0
        self._calls: list[_Call] = []
        self.sim_params = node.create_client(SetParameters, f'{sim_node}/set_parameters')
        self.policy_params = node.create_client(SetParameters, f'{policy_node}/set_parameters')
        self.policy_get = node.create_client(GetParameters, f'{policy_node}/get_parameters')
        self.encoder_get = node.create_client(GetParameters, f'{encoder_node}/get_parameters')
        self.reset_client = node.create_client(Trigger, '/sim/reset')
        self.stage = 'idle'          # idle | waiting_graph | configuring | warming | resetting | flying | closing
        self._graph_deadline = math.inf
        self.spec: LandingSpec | None = None
        self.episode: int | None = None
        # the latest /sim/landing result that came while /sim/reset's answer was on its way (a short landing on a
        # loaded machine ends before the answer is handled), for the answer to claim when it names that episode
        self._early_landing: dict[str, Any] | None = None
        self.started_at = math.inf
        self.start_xy: np.ndarray | None = None
        self.last_xy: np.ndarray | None = None
        self.path_m = 0.0                    # path flown in the landing in flight (m)
        self._path_last: tuple[np.ndarray, float | None] | None = None      # last /odom position and its stamp
        self.pads: np.ndarray | None = None
        self.boxes: list[dict[str, Any]] = []
        self.recorder = None
        self.bag: str | None = None
        self._pending_config = 0
        self._warm_until = math.inf
        self._close_at = math.inf
        self._view_dirty = True
        self.error: str | None = None
        self.save_error: str | None = None      # the last step could not be saved (shown until a step is)
        problem = self._set_cues(False)         # no cues unless a landing of the cue condition flies
        if problem:
            node.get_logger().error(f'study: {problem}')

    # ------------------------------------------------------------------ inputs (any thread)
    def submit(self, msg: StudyMessage) -> None:
        """A study step from the pilot page (web server thread): queued for the node's timer.

        One begin at a time: while one waits, more are refused (the first with one page error and one line).
        """
        if msg.action == 'begin':
            with self._begin_lock:
                duplicate = self._begin_pending
                if duplicate:
                    self._begin_duplicates += 1
                    first = self._begin_duplicates == 1
                self._begin_pending = True
            if duplicate:
                if first:
                    self._push_event({'type': 'study_error', 'message': 'a participant is being opened already; '
                                                                        'more begin steps are refused until it is'})
                    self._warn('begin_duplicate', 'study: begin refused: another begin is waiting')
                return
        try:
            self.inbox.put_nowait(msg)
        except queue.Full:
            if msg.action == 'begin':
                with self._begin_lock:
                    self._begin_pending = False
            self._warn('inbox_full', f'study: more than {INBOX_SIZE} page steps waiting; {msg.action} dropped')

    def _warn(self, key: str, text: str, level: str = 'warning') -> None:
        """A log line, at most one per `key` per WARNING_PERIOD_S (with how many were held back)."""
        held = self._warnings(key)
        if held is not None:
            getattr(self.node.get_logger(), level)(text + (f' ({held} more like it not logged)' if held else ''))

    def page_lost(self) -> None:
        """The pilot page went away (web server thread)."""
        try:
            self.inbox.put_nowait(('page_lost', None))
        except queue.Full:
            pass

    @property
    def flying(self) -> bool:
        """Whether the pilot's keys fly the vehicle now (a landing is in flight)."""
        return self.stage == 'flying'

    def note_scene(self, boxes: list[dict[str, Any]]) -> None:
        """The scene's pad boxes (from /sim/scene: id, centre p, size s, quaternion q)."""
        pads = sorted((b for b in boxes if b['ns'] == 'platforms'), key=lambda b: b['id'])
        self.boxes = [{'id': b['id'], 'p': b['p'], 's': b['s'],
                       'yaw': heading(b['q'])} for b in pads]
        self.pads = np.array([[b['p'][0], b['p'][1], b['p'][2] + b['s'][2] / 2] for b in pads]) if pads else None

    def note_odom(self, position: np.ndarray, stamp_s: float | None = None) -> None:
        """The vehicle's position (x, y, z in odom, from /odom, stamped `stamp_s`: None when unset): where it is,
        and the path of a landing in flight (module doc). Without stamps every step longer than JUMP_M is taken
        for a teleport."""
        p = np.asarray(position, dtype=float).reshape(-1)[:3]
        self.last_xy = p[:2].copy()
        if self.stage != 'flying':
            return
        if self.start_xy is None:
            self.start_xy = self.last_xy.copy()
        if self._path_last is not None:
            last, last_t = self._path_last
            dt = None if stamp_s is None or last_t is None else stamp_s - last_t
            if dt is not None and dt <= 0:
                return                      # older than (or as old as) the last one: no step
            step = float(np.linalg.norm(p - last))
            if step <= JUMP_M or (dt is not None and step / dt <= MAX_SPEED_MPS):
                self.path_m += step
        self._path_last = (p, stamp_s)

    # ------------------------------------------------------------------ timer (node thread)
    def tick(self) -> None:
        """Run queued page steps, finished service calls, timeouts; publish the view when it changed."""
        for call in list(self._calls):
            if call not in self._calls:     # an earlier answer in this loop failed the step: the rest went with it
                continue
            if call.future.done():
                self._calls.remove(call)
                try:
                    result = call.future.result()
                except Exception as exc:  # noqa: BLE001 - a failed call fails the step, reported below
                    self._fail(f'{call.what} failed: {exc}')
                    continue
                call.on_done(result)
            elif time.monotonic() > call.deadline:
                if call.retry():
                    self._warn(f'retry {call.what}', f'study: {call.what}: no answer within {call.timeout_s:.0f} s; '
                                                     f'sent again (try {call.tries} of {SERVICE_RETRIES + 1})')
                    continue
                self._calls.remove(call)
                self._fail(f'{call.what}: no answer within {call.timeout_s:.0f} s ({call.tries} tries)')
        while True:
            try:
                msg = self.inbox.get_nowait()
            except queue.Empty:
                break
            if isinstance(msg, tuple):
                if msg[0] == 'page_lost' and self.stage not in ('idle', 'closing'):
                    self._abort('the pilot page went away')
                continue
            try:
                self._step(msg)
                self.save_error = None
            except StudyError as exc:
                self._push_event({'type': 'study_error', 'message': str(exc)})
                self._warn(f'refused {msg.action}', f'study: {msg.action} refused: {exc}')
            except OSError as exc:          # a full or read-only disk: nothing half written, the step not taken
                self.save_error = (f'could not save ({exc.strerror or exc}): {msg.action} was not taken and nothing '
                                   'was lost; tell the experimenter, then try again')
                self._push_event({'type': 'study_error', 'message': self.save_error})
                self._warn(f'not saved {msg.action}', f'study: {msg.action} not saved: {exc}', 'error')
            finally:
                if msg.action == 'begin':
                    with self._begin_lock:
                        self._begin_pending, self._begin_duplicates = False, 0
            self._report_log_problem()
            self._view_dirty = True
        now = time.monotonic()
        if self.stage == 'waiting_graph':
            self._configure()
        if self.stage == 'warming' and now >= self._warm_until:
            self._reset_sim()
        if self.stage == 'flying' and now - self.started_at > self.cfg.landing_timeout_s:
            self._abort(f'no landing result within {self.cfg.landing_timeout_s:.0f} s')
        if self.stage == 'closing' and now >= self._close_at:
            self._close_bag()
            self.stage = 'idle'
            self._view_dirty = True
        if self._view_dirty:
            self._view_dirty = False
            self._publish_view(self.view())

    def view(self) -> dict[str, Any]:
        """The page's study view (phase, texts, counters); a participant ID prompt when none is open."""
        if self.session is None:
            v = {'type': 'study', 'phase': 'participant', 'study': self.cfg.name, 'intro': self.cfg.intro_text}
            if self.save_error:
                v['error'] = self.save_error
            return v
        v = self.session.view()
        v['stage'] = self.stage          # in_flight comes from the session: a landing is active exactly then
        if self.error or self.save_error:
            v['error'] = self.error or self.save_error
        return v

    def _report_log_problem(self) -> None:
        """A step saved whose protocol.log line was not: the operator and the page hear it (the step stands)."""
        problem = None if self.session is None else self.session.take_log_problem()
        if problem:
            self.node.get_logger().error(f'study: {self.session.pid}: {problem}; the step itself is saved')
            self._push_event({'type': 'study_error', 'message': f'saved, but {problem}; tell the experimenter'})

    # ------------------------------------------------------------------ steps
    def _step(self, msg: StudyMessage) -> None:
        action, data = msg.action, msg.data
        if action == 'begin':
            pid = check_participant_id(data.get('participant'))
            if self.session is not None:            # one participant at a time, until they are done
                if self.session.pid == pid:
                    raise StudyError(f'participant {pid} is open already')
                if self.stage not in ('idle', 'closing'):
                    raise StudyError('a landing is in flight; finish it first')
                phase = self.session.phase
                if phase != 'done':
                    raise StudyError(f'participant {self.session.pid} has not finished (at {phase}); the station '
                                     'takes the next participant once they are done, or after a restart')
            session = StudySession(self.cfg, self.text, self.root, pid)
            self._close_bag()
            self.stage = 'idle'
            self.session = session
            self.error = None
            with self._begin_lock:
                refused = self._begin_duplicates
            self.node.get_logger().info(f'study: participant {self.session.pid} at {self.session.phase} '
                                        f'({self.session.order})'
                                        + (f'; {refused} duplicate begin step(s) refused' if refused else ''))
            return
        if self.session is None:
            raise StudyError('enter a participant ID first')
        if action == 'consent':
            self.session.consent()
        elif action == 'stop_practice':
            self.session.stop_practice()
        elif action == 'sus':
            self.session.submit_sus(data.get('answers'))
        elif action == 'survey':
            self.session.submit_survey(data.get('answers'))
            self.node.get_logger().info(f'study: participant {self.session.pid} done')
        elif action == 'start':
            self._start_landing()

    def _start_landing(self) -> None:
        if self.stage not in ('idle', 'closing'):
            raise StudyError('a landing is in flight already')
        self._close_bag()
        spec = self.session.next_landing()
        bag = None
        if self.cfg.record_bags:
            bag = self.session.store.new_bag_path(spec.name)
        self.spec = self.session.start_landing(bag=None if bag is None else bag.name)
        self.bag = None if bag is None else str(bag)
        self.episode, self.start_xy, self.error = None, None, None
        self._early_landing = None
        self.stage = 'waiting_graph'       # until sim_node (and for an assisted landing policy_node) answer
        self._graph_deadline = time.monotonic() + GRAPH_WAIT_S
        self._configure()

    def _graph_missing(self) -> list[str]:
        missing = [name for name, c in (('sim_node parameters', self.sim_params), ('/sim/reset', self.reset_client))
                   if not c.service_is_ready()]
        if self.spec is not None and self.spec.assisted and not self.policy_params.service_is_ready():
            missing.append('policy_node (the assisted condition needs it)')
        return missing

    def _configure(self) -> None:
        """Once the graph's services answer: set the landing's parameters (then the bag, then /sim/reset)."""
        missing = self._graph_missing()
        if missing:
            if time.monotonic() > self._graph_deadline:
                self._fail(f'not available after {GRAPH_WAIT_S:.0f} s: {", ".join(missing)}')
            return
        spec = self.spec
        self.stage = 'configuring'
        self._pending_config = 0
        sim = [Parameter('scene_seed', value=int(self.cfg.scene_seed)),
               Parameter('goal_index', value=int(spec.goal_index)), Parameter('auto_reset', value=False)]
        self._set_params('sim_node', self.sim_params, sim)
        if self.policy_params.service_is_ready():
            self._set_params('policy_node', self.policy_params, [Parameter('assist_enabled', value=spec.assisted)])
            if spec.assisted:
                self._check_policy_mode()
        problem = self._set_cues(spec.cues)
        if problem:
            self._fail(problem)
            return
        self.node.get_logger().info(f'study: {self.session.pid} {spec.name} ({spec.condition}, goal pad '
                                    f'{spec.goal_index})')

    def _set_cues(self, on: bool) -> str | None:
        """Switch the station's cue parameters (its own: the node that hosts the study) on or off; why not, or
        None. A node without them (no pilot station) has no cues to switch."""
        names = [n for n in CUE_PARAMETERS if self.node.has_parameter(n)]
        change = [Parameter(n, value=bool(on)) for n in names if self.node.get_parameter(n).value != bool(on)]
        if not change:
            return None
        result = self.node.set_parameters_atomically(change)
        if result.successful:
            return None
        return f"pilot_station refused {', '.join(p.name for p in change)}: {result.reason}"

    def _set_params(self, what: str, client: Any, params: list[Parameter]) -> None:
        if not client.service_is_ready():
            self._fail(f'{what} parameter service not available')
            return
        self._pending_config += 1
        req = SetParameters.Request(parameters=[p.to_parameter_msg() for p in params])

        def done(result: Any) -> None:
            bad = [f'{p.name}: {r.reason}' for p, r in zip(params, result.results) if not r.successful]
            if bad:
                self._fail(f'{what} refused ' + '; '.join(bad))
                return
            self._pending_config -= 1
            if self._pending_config == 0 and self.stage == 'configuring':
                self._open_bag()
        self._calls.append(_Call(f'setting {what} parameters', client.call_async(req), done,
                                 again=lambda: client.call_async(req)))

    def _check_policy_mode(self) -> None:
        """The assisted block flies the study file's assistant: policy_node's mode and model, encoder_node's model."""
        checks = [(self.policy_get, 'policy_node', ['mode', 'model_path'],
                   {'mode': self.cfg.assistant_mode, 'model_path': self.cfg.policy_model})]
        if self.cfg.assistant_mode == 'latent' and self.cfg.encoder_model:
            checks.append((self.encoder_get, 'encoder_node', ['model_path'], {'model_path': self.cfg.encoder_model}))
        for client, what, names, wanted in checks:
            if not client.service_is_ready():
                if what == 'encoder_node':
                    self._fail('encoder_node is not running; the study file names its model')
                continue

            def done(result: Any, what: str = what, names: list[str] = names, wanted: dict = wanted) -> None:
                got = dict(zip(names, (v.string_value for v in result.values)))
                for name, want in wanted.items():
                    have = got.get(name, '')
                    same = have == want if name == 'mode' else _same_file(have, want)
                    if not same:
                        self._fail(f'{what} flies {name} {have or "(shipped)"!r}, the study file asks for '
                                   f'{want or "(shipped)"!r}')
                        return
            req = GetParameters.Request(names=names)
            self._calls.append(_Call(f'reading {what} parameters', client.call_async(req), done,
                                     again=lambda client=client, req=req: client.call_async(req)))

    def _open_bag(self) -> None:
        if self.bag is not None:
            from .study_bag import open_landing_bag
            try:
                self.recorder = open_landing_bag(self.node, self.bag, self.cfg.bag_topics)
            except Exception as exc:  # noqa: BLE001 - no bag: the landing is not flown (nothing lost)
                self._fail(f'cannot record the landing bag {self.bag}: {exc}')
                return
        self.stage = 'warming'
        self._warm_until = time.monotonic() + (BAG_WARMUP_S if self.recorder is not None else 0.0)

    def _reset_sim(self) -> None:
        if not self.reset_client.service_is_ready():
            self._fail('/sim/reset not available (is sim_node running?)')
            return
        self.stage = 'resetting'

        def done(result: Any) -> None:
            m = EPISODE_RE.match(result.message or '')
            if not result.success or m is None:
                self._fail(f'/sim/reset: {result.message!r}')
                return
            episode, goal = int(m.group(1)), int(m.group(2))
            if goal != self.spec.goal_index:
                self._fail(f'sim_node started goal pad {goal}, the landing flies {self.spec.goal_index}')
                return
            self.episode = episode
            self.stage = 'flying'
            self.started_at = time.monotonic()
            self.start_xy = None
            self.path_m, self._path_last = 0.0, None
            if self.keys is not None:
                self.keys.start()
            self._view_dirty = True
            early, self._early_landing = self._early_landing, None
            if early is not None and early['episode'] == episode:    # the episode ended before this answer came
                self.on_landing(early)
        self._calls.append(_Call('/sim/reset', self.reset_client.call_async(Trigger.Request()), done))

    def on_landing(self, landing: dict[str, Any]) -> bool:
        """A /sim/landing result (node thread); True when it was the landing in flight (recorded; the page is told).

        One that comes while /sim/reset's answer is awaited is kept for that answer (the episode it names may be this
        one) and recorded when the answer comes."""
        episode = landing.get('episode')
        if self.stage == 'resetting' and self.session is not None and isinstance(episode, int):
            self._early_landing = landing
            return False
        if self.stage != 'flying' or self.session is None or episode != self.episode:
            return False
        spec = self.spec
        start_pad = self._pad_under(self.start_xy)
        keys = self.keys.stop() if self.keys is not None else None
        measures = {'path_length_m': self.path_m if self._path_last is not None else None,
                    'key_presses': None if keys is None else keys[0],
                    'corrective_keys': None if keys is None else keys[1]}
        try:
            row = self.session.record_landing(landing, start_pad=start_pad, episode=self.episode,
                                              bag=None if self.bag is None else Path(self.bag).name,
                                              measures=measures)
        except (StudyError, OSError) as exc:
            self._fail(f'landing not recorded: {exc}')
            return False
        self._cues_off()
        self._report_log_problem()          # the row is saved: recorded, even where its log line is missing
        if spec.block == PRACTICE_BLOCK:
            fb = practice_feedback(landing, self.pads, self.last_xy)
            self.session.last_feedback = fb
            self._push_event({'type': 'study_feedback', **fb})
        self.node.get_logger().info(f"study: {self.session.pid} {spec.name} recorded: {row['outcome']} "
                                    f"error {row['error_m']} m")
        self.stage = 'closing'
        self._close_at = time.monotonic() + BAG_TAIL_S
        self._view_dirty = True
        self._push_event(landing_feedback(landing, 'study'))      # "Landing recorded", no result
        return True

    def _pad_under(self, xy: np.ndarray | None) -> int | None:
        """The pad whose footprint holds `xy` (scene boxes from /sim/scene), else None."""
        if xy is None:
            return None
        for b in self.boxes:
            local = rotate_xy(np.asarray(xy) - np.asarray(b['p'][:2]), -b['yaw'])    # into the pad's frame
            if np.all(np.abs(local) <= np.asarray(b['s'][:2]) / 2):
                return int(b['id'])
        return None

    # ------------------------------------------------------------------ failures
    def _fail(self, why: str) -> None:
        self.error = why
        self.node.get_logger().error(f'study: {why}')
        self._push_event({'type': 'study_error', 'message': why})
        self._abort(why)

    def _cues_off(self) -> None:
        """The landing is over: the cues go off (a refusal is logged; the next landing's start tries again)."""
        problem = self._set_cues(False)
        if problem:
            self.node.get_logger().error(f'study: {problem}')

    def _abort(self, why: str) -> None:
        if self.session is not None and self.session.active is not None:
            self.session.abort_landing(why)
            self._report_log_problem()
        if self.keys is not None:
            self.keys.stop()
        self._cues_off()
        self._calls.clear()
        self._close_bag()
        self.stage = 'idle'
        self.episode = None
        self._early_landing = None
        self._view_dirty = True

    def _close_bag(self) -> None:
        rec, self.recorder = self.recorder, None
        if rec is None:
            return
        from .study_bag import close_landing_bag
        try:
            close_landing_bag(self.node, rec)
        except Exception as exc:  # noqa: BLE001 - report; the row (if any) is written already
            self.node.get_logger().error(f'study: closing the landing bag failed: {exc}')

    def close(self) -> None:
        """Station shutting down: a landing in flight is not recorded; its bag is closed."""
        if self.stage not in ('idle', 'closing'):
            self._abort('station stopped')
        self._close_bag()
