"""Simulated study participants: a pilot family with a drawn skill flies the real station over its WebSocket.

A participant connects to the station like the page does (same Origin rules, the same ``keys`` and
``study`` messages), goes through the whole protocol and flies each landing with a simulated pilot of
assist_sim.pilots (family and skill ``beta`` per participant, conformance ``alpha``): it reads the pose
from the station's state messages and the goal pad from its scene, turns the pilot's velocity into held
keys (W/A/S/D, arrows; a key is held while the pilot's command on that axis is above half the key
speed) and perceives the assistant as the difference between the vehicle's velocity and its own keys.
In a landing of the assisted_cues condition the pilot also reads the intent cues the station shows it (the
``cues`` of the station's state messages: the highlighted goal pad, the descent light) as assist_sim.cues
says, each landing with the participant's ``cue_trust``; in the other conditions the station shows none and
the pilot is the same as without cues.
Questionnaire answers are scripted from the participant's skill and what it saw of its own landings
(how far from the goal pad the drone came to rest), so they correlate with skill and performance.

A dropped connection (station restarted, socket closed) is reconnected and the protocol goes on where
the station says it stands.
"""
from __future__ import annotations

import asyncio
import json
import logging
import time
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any

import aiohttp
import numpy as np

from assist_common.frames import enu_to_flu, heading

from .study import CUE_CONDITION, SURVEY, SUS_ITEMS, phase_block

if TYPE_CHECKING:
    from assist_sim.cues import Cue

log = logging.getLogger(__name__)

KEY_SPEED_FRACTION = 0.5          # a key is held while the pilot's command on its axis exceeds this x key speed
VERTICAL_THRESHOLD_MPS = 0.1
HEARTBEAT_S = 0.25
ASSIST_PERCEPTION_MPS = 0.25      # velocity beyond the keys' own that the participant takes for the assistant
STEP_TIMEOUT_S = 30.0             # a study step the station does not answer within this (wall) is an error
# a landing not in flight this long after it began is an error: the station waits up to GRAPH_WAIT_S (60 s) for the
# graph's nodes, then sets their parameters and resets the world
FLIGHT_START_TIMEOUT_S = 90.0
DEFAULT_FAMILIES = ('paper', 'delay', 'tapper', 'bang_bang', 'keyboard', 'cautious')
CUE_TRUST = (0.5, 1.0)            # a participant's cue_trust is drawn uniformly between these
CUE_TRUST_SALT = 0x637565         # its own generator: drawing it changes none of the other profile values


def step_key(view: dict[str, Any] | None) -> tuple | None:
    """Which step of the protocol a study view shows (participant, phase, trial, a landing in flight): a study
    action's result is a view with another key."""
    return None if view is None else tuple(view.get(k) for k in ('participant', 'phase', 'trial', 'in_flight'))


class ParticipantError(RuntimeError):
    """The station refused a step or stopped answering."""


@dataclass
class Profile:
    """Who a simulated participant is: ID, pilot family, skill, conformance, seed and practice habit."""

    pid: str
    family: str
    beta: float                   # skill in [0, 1] (the paper's beta)
    alpha: float                  # conformance to the assistant in [0, 1]
    seed: int
    practice: int                 # practice landings flown before finishing practice
    experience: float             # self-rated experience in [0, 1] (noisy in skill)
    cue_trust: float = 1.0        # chance per landing of reading the cues, where the station shows them (assisted_cues)
    extra: dict[str, Any] = field(default_factory=dict)


def draw_profiles(n: int, seed: int, families: tuple[str, ...] = DEFAULT_FAMILIES, practice: int = 2,
                  id_prefix: str = 'S', cue_trust: tuple[float, float] = CUE_TRUST) -> list[Profile]:
    """`n` participants with a spread of skills: betas on a jittered grid over [0.1, 0.9], families in turn, a
    cue_trust uniform in `cue_trust` (from its own generator of `seed`)."""
    rng = np.random.default_rng(seed)
    trusts = np.random.default_rng([seed, CUE_TRUST_SALT]).uniform(cue_trust[0], cue_trust[1], n)
    grid = (np.arange(n) + rng.uniform(0.2, 0.8, n)) / max(n, 1)
    betas = 0.1 + 0.8 * rng.permutation(grid)
    out = []
    for i in range(n):
        beta = float(np.clip(betas[i], 0.05, 0.95))
        experience = float(np.clip(beta + rng.normal(0.0, 0.12), 0.0, 1.0))
        out.append(Profile(pid=f'{id_prefix}{i + 1:02d}', family=families[i % len(families)], beta=round(beta, 3),
                           alpha=round(float(rng.uniform(0.3, 0.7)), 3), seed=int(rng.integers(2 ** 31 - 1)),
                           practice=int(max(1, min(practice, 1 + rng.integers(practice + 1)))),
                           experience=round(experience, 3), cue_trust=round(float(trusts[i]), 3)))
    return out


# ----------------------------------------------------------------------------------------- answers
def _likert(rng: np.random.Generator, x: float, noise: float = 0.6) -> int:
    """A 1-5 answer for agreement level x in [0, 1] with answer noise."""
    return int(np.clip(round(1 + 4 * x + rng.normal(0.0, noise)), 1, 5))


def sus_answers(rng: np.random.Generator, liking: float) -> list[int]:
    """Ten SUS answers for how usable the block felt (liking in [0, 1]): odd items agree, even items disagree."""
    return [_likert(rng, liking) if i % 2 == 0 else _likert(rng, 1.0 - liking) for i in range(len(SUS_ITEMS))]


def survey_answers(rng: np.random.Generator, profile: Profile, felt: dict[str, float]) -> dict[str, Any]:
    """The concluding survey from the profile's experience and how each condition felt (0 bad .. 1 good)."""
    e = profile.experience
    hours = _likert(rng, e, 0.5)
    a: dict[str, Any] = {'1': 1 if hours >= 2 else 2, '2': hours, '3': _likert(rng, e, 0.5),
                         '4': [1] if hours >= 2 else [], '5': _likert(rng, e, 0.7), '6': _likert(rng, e, 0.5),
                         '7': [1, 2] if rng.random() < 0.7 else [3]}
    un, asd = felt.get('unassisted', 0.5), felt.get('assisted', 0.5)
    prefer = 0.5 + 0.5 * (asd - un)
    statements = {8: un, 9: asd, 10: 1 - un, 11: 1 - asd, 12: 1 - un, 13: 1 - asd, 14: prefer, 15: prefer,
                  16: asd, 17: 1 - asd, 18: 1 - prefer, 19: prefer, 20: 1 - prefer, 21: 0.3 + 0.4 * e}
    for q, level in statements.items():
        a[str(q)] = _likert(rng, float(np.clip(level, 0.0, 1.0)))
    assert set(a) == {str(q['id']) for q in SURVEY}
    return a


# ----------------------------------------------------------------------------------------- keys
def keys_for(u: np.ndarray, speed: float) -> list[str]:
    """Held browser keys for a body-FLU velocity command (FLU = ENU at yaw 0)."""
    keys = []
    thr = KEY_SPEED_FRACTION * speed
    if u[0] > thr:
        keys.append('KeyW')
    elif u[0] < -thr:
        keys.append('KeyS')
    if u[1] > thr:
        keys.append('KeyA')
    elif u[1] < -thr:
        keys.append('KeyD')
    if u[2] > VERTICAL_THRESHOLD_MPS:
        keys.append('ArrowUp')
    elif u[2] < -VERTICAL_THRESHOLD_MPS:
        keys.append('ArrowDown')
    return keys


def key_velocity(keys: list[str], speed: float, speed_z: float) -> np.ndarray:
    """The velocity the station commands for held keys (what the participant expects the drone to do)."""
    v = np.zeros(3)
    table = {'KeyW': (0, speed), 'KeyS': (0, -speed), 'KeyA': (1, speed), 'KeyD': (1, -speed),
             'ArrowUp': (2, speed_z), 'ArrowDown': (2, -speed_z)}
    for k in keys:
        axis, value = table[k]
        v[axis] = value
    return v


# ----------------------------------------------------------------------------------------- flying
def cue_shown(cues: dict | None) -> bool:
    """Whether the station's state message shows any intent cue (goal pad, light or push)."""
    return bool(cues) and any(v is not None for v in cues.values())


def cue_from_view(cues: dict | None) -> Cue | None:
    """The cue a participant sees in the station's state message (its ``cues``) as assist_sim.cues.Cue: the goal
    pad while it is drawn known (sure or unsure, with its sigma), the light while it is green (True) or red
    (False); None when the station shows no cue."""
    from assist_sim.cues import Cue
    if not cues:
        return None
    goal = cues.get('goal')
    known = isinstance(goal, dict) and goal.get('state') in ('sure', 'unsure') and goal.get('p') is not None
    light = {'ok': True, 'hold': False}.get(cues.get('descent'))
    if not known and light is None:
        return None
    return Cue(np.asarray(goal['p'], dtype=float) if known else None,
               float(goal.get('sigma_m', np.inf)) if known else np.inf, light)


class Flyer:
    """One landing of a participant: its pilot model turned into held keys, step by step from the pose."""

    def __init__(self, profile: Profile, landing: int, scene: dict, start: np.ndarray, speed: float,
                 speed_z: float, reads_cues: bool = False):
        """`reads_cues`: the landing shows cues (assisted_cues); its pilot reads them with the profile's cue_trust."""
        from assist_sim.cues import CueConfig
        from assist_sim.pilots import make_pilot
        self.pads = np.array([[b['p'][0], b['p'][1], b['p'][2] + b['s'][2] / 2] for b in scene['platforms']])
        self.goal = self.pads[int(scene['goal'])]
        self.speed, self.speed_z = speed, speed_z
        rng = np.random.default_rng([profile.seed, landing])
        self.reads_cues = reads_cues
        self.pilot = make_pilot(profile.family, profile.alpha, profile.beta, rng=rng, pads=self.pads,
                                cues=CueConfig(trust=profile.cue_trust) if reads_cues else None)
        self.pilot.reset(self.goal, np.asarray(start, dtype=float))
        self.keys: list[str] = []

    @property
    def period_s(self) -> float:
        """Sim seconds per pilot step."""
        return 1.0 / self.pilot.cfg.control_hz

    def step(self, pose: dict, cues: dict | None = None) -> list[str]:
        """The keys to hold after seeing `pose` (p, v, q in odom ENU) and the station's `cues` (its state
        message's; read in a cue landing only): the pilot's command, the assistant perceived as the velocity
        beyond what the held keys command."""
        if self.reads_cues:
            self.pilot.see_cue(cue_from_view(cues))
        pos, vel = np.array(pose['p'], dtype=float), np.array(pose['v'], dtype=float)
        v_body = enu_to_flu(vel, heading(pose['q']))
        extra = v_body - key_velocity(self.keys, self.speed, self.speed_z)
        a = extra if float(np.linalg.norm(extra)) > ASSIST_PERCEPTION_MPS else None
        self.keys = keys_for(self.pilot.act(pos, a), self.speed)
        return self.keys

    def distance(self, pose: dict) -> float:
        """Horizontal distance from the goal pad's centre (what the participant sees of its landing)."""
        return float(np.linalg.norm(np.array(pose['p'], dtype=float)[:2] - self.goal[:2]))


def felt(distances: list[float]) -> float:
    """How well a condition went as the participant saw it (0..1, from its own landings' distances)."""
    return float(np.clip(1.0 - np.median(distances or [1.5]) / 1.5, 0.0, 1.0))


# ----------------------------------------------------------------------------------------- client
class Participant:
    """Drives one simulated participant through the station's protocol over its WebSocket."""

    def __init__(self, url: str, profile: Profile, real_time_factor: float = 1.0, connect_timeout_s: float = 60.0,
                 on_landing=None):
        self.url = url.rstrip('/') + '/'
        self.on_landing = on_landing or (lambda: None)      # called after each landing flown (progress)
        self.profile = profile
        self.rtf = float(real_time_factor)
        self.connect_timeout_s = connect_timeout_s
        self.rng = np.random.default_rng(profile.seed)
        self.ws: aiohttp.ClientWebSocketResponse | None = None
        self.hello: dict | None = None
        self.scene: dict | None = None
        self.state: dict | None = None
        self.view: dict | None = None
        self.errors: list[str] = []
        self.view_changed = asyncio.Event()
        self.outcomes: dict[str, list[float]] = {'unassisted': [], 'assisted': []}
        self.cue_steps: dict[str, list[int]] = {}     # condition -> [pilot steps flown, steps with a cue shown]
        self.reconnects = 0
        self.landings_flown = 0

    # ---------------------------------------------------------------- connection
    async def _connect(self, session: aiohttp.ClientSession) -> None:
        """Connect as the pilot; while the station gives only a view (the previous pilot's role is still
        reserved for its page), close and try again until connect_timeout_s."""
        origin = self.url.rstrip('/')
        end = time.monotonic() + self.connect_timeout_s
        while True:
            try:
                self.ws = await session.ws_connect(self.url + 'ws', headers={'Origin': origin}, heartbeat=None)
            except (aiohttp.ClientError, OSError) as exc:
                if time.monotonic() > end:
                    raise ParticipantError(f'cannot reach the station at {self.url}: {exc}') from exc
                await asyncio.sleep(0.5)
                continue
            self.hello, self.view = None, None
            self._reader = asyncio.get_running_loop().create_task(self._read(self.ws))
            await self._wait(lambda: self.hello is not None, 'hello')
            if self.hello.get('role') == 'pilot':
                return
            await self.ws.close()
            if time.monotonic() > end:
                raise ParticipantError(f"the station kept this participant view only: {self.hello.get('reason')}")
            await asyncio.sleep(1.0)

    async def _read(self, ws: aiohttp.ClientWebSocketResponse) -> None:
        async for msg in ws:
            if msg.type != aiohttp.WSMsgType.TEXT:
                continue
            try:
                m = json.loads(msg.data)
            except ValueError:
                continue
            t = m.get('type')
            if t == 'hello':
                self.hello = m
            elif t == 'scene':
                self.scene = m
            elif t == 'state':
                self.state = m
            elif t == 'study':
                self.view = m
                self.view_changed.set()
            elif t == 'study_error':
                self.errors.append(m.get('message', ''))
                self.view_changed.set()

    async def _wait(self, cond, what: str, timeout_s: float = STEP_TIMEOUT_S) -> None:
        end = time.monotonic() + timeout_s
        while not cond():
            if self.ws is None or self.ws.closed:
                raise ConnectionResetError(f'station connection lost while waiting for {what}')
            if time.monotonic() > end:
                raise ParticipantError(f'the station did not show {what} within {timeout_s:.0f} s '
                                       f'(errors: {self.errors[-3:]})')
            self.view_changed.clear()
            try:
                await asyncio.wait_for(self.view_changed.wait(), 0.05)
            except TimeoutError:
                pass

    async def _send(self, obj: dict) -> None:
        if self.ws is None or self.ws.closed:
            raise ConnectionResetError('station connection lost')
        await self.ws.send_str(json.dumps(obj))

    async def _step(self, action: str, **data: Any) -> None:
        """Send a study step and wait until the station's view moves on to another step (`step_key`) or reports an
        error; a view of the same step (its stage changing as the last landing's bag closes, say) is not the result
        of this one, and taking it for one would send the step twice."""
        before = step_key(self.view)
        n_err = len(self.errors)
        await self._send({'type': 'study', 'action': action, **data})
        await self._wait(lambda: step_key(self.view) != before or len(self.errors) > n_err, f'the result of {action}')
        if len(self.errors) > n_err:
            raise ParticipantError(f'station refused {action}: {self.errors[-1]}')

    # ---------------------------------------------------------------- protocol
    async def run(self, max_reconnects: int = 5) -> dict[str, Any]:
        """Go through the whole protocol; returns what happened (landings flown, reconnects)."""
        async with aiohttp.ClientSession() as session:
            while True:
                try:
                    await self._connect(session)
                    await self._protocol()
                    break
                except (ConnectionResetError, aiohttp.ClientError, ConnectionError) as exc:
                    self.reconnects += 1
                    if self.reconnects > max_reconnects:
                        raise ParticipantError(f'station connection lost {self.reconnects} times: {exc}') from exc
                    log.warning('%s: %s; reconnecting', self.profile.pid, exc)
                    await asyncio.sleep(1.0)
                finally:
                    if self.ws is not None:
                        await self.ws.close()
        return {'participant': self.profile.pid, 'landings_flown': self.landings_flown,
                'reconnects': self.reconnects, 'profile': asdict(self.profile), 'cue_steps': self.cue_steps}

    async def _protocol(self) -> None:
        p = self.profile
        await self._wait(lambda: self.view is not None, 'the study view')
        if self.view.get('participant') != p.pid or self.view.get('phase') == 'participant':
            await self._step('begin', participant=p.pid)
        while True:
            v = self.view
            phase = v['phase']
            if phase == 'consent':
                await self._step('consent')
            elif phase == 'practice' and v['trial'] > p.practice:
                await self._step('stop_practice')
            elif phase == 'practice' or (phase.startswith('block') and phase_block(phase)):
                await self._fly(v)
            elif phase.startswith('sus') and phase_block(phase):
                await self._step('sus', answers=sus_answers(self.rng, felt(self.outcomes.get(v['condition'], []))))
            elif phase == 'survey':
                how = {c: felt(d) for c, d in self.outcomes.items()}
                await self._step('survey', answers=survey_answers(self.rng, p, how))
            elif phase == 'done':
                return
            else:
                raise ParticipantError(f'unexpected study phase {phase!r}')

    # ---------------------------------------------------------------- flying
    async def _fly(self, v: dict) -> None:
        key = (v['phase'], v['trial'])
        await self._wait(lambda: not self.view.get('in_flight') or not self._same_landing(key),
                         'the landing to be startable')
        if not self._same_landing(key):
            return
        await self._step('start')
        await self._wait(lambda: self.view.get('stage') == 'flying' or not self._same_landing(key),
                         'the landing in flight', timeout_s=FLIGHT_START_TIMEOUT_S)
        if not self._same_landing(key):
            return
        await self._wait(lambda: self.state is not None and self.state.get('pose') is not None
                         and self.scene is not None and self.scene.get('goal') is not None, 'pose and scene')
        flyer = Flyer(self.profile, self.landings_flown, self.scene, np.array(self.state['pose']['p']),
                      float(self.hello.get('speed', 1.0)), float(self.hello.get('speed_z', 0.5)),
                      reads_cues=v.get('condition') == CUE_CONDITION)
        period = flyer.period_s / self.rtf
        keys: list[str] = []
        last_sent = 0.0
        next_t = time.monotonic()
        while self.view.get('stage') == 'flying' and self._same_landing(key):
            if self.ws is None or self.ws.closed:
                raise ConnectionResetError('station connection lost during a landing')
            cues = self.state.get('cues')
            seen = self.cue_steps.setdefault(v.get('condition', ''), [0, 0])
            seen[0] += 1
            seen[1] += cue_shown(cues)
            new = flyer.step(self.state['pose'], cues)
            now = time.monotonic()
            if new != keys or now - last_sent >= HEARTBEAT_S:
                keys = list(new)
                last_sent = now
                await self._send({'type': 'keys', 'down': keys})
            next_t += period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))
            if time.monotonic() - next_t > 1.0:
                next_t = time.monotonic()
        await self._send({'type': 'keys', 'down': []})
        if self.state and self.state.get('pose'):
            self.outcomes.setdefault(v.get('condition', 'unassisted'), []).append(flyer.distance(self.state['pose']))
        self.landings_flown += 1
        self.on_landing()

    def _same_landing(self, key: tuple) -> bool:
        return (self.view.get('phase'), self.view.get('trial')) == key


def run_participant(url: str, profile: Profile, real_time_factor: float = 1.0) -> dict[str, Any]:
    """Run one participant to the end of the protocol (blocking)."""
    return asyncio.run(Participant(url, profile, real_time_factor).run())
