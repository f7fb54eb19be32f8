"""Episode sequencing for landings on a real (or SITL) autopilot, without rclpy.

In MAVLink / ArduPilot-SITL set-ups every landing episode starts landed and disarmed, so somebody
has to put the vehicle in the air before the pilot (simulated or human) and the assistant can fly
the landing: GUIDED, arm (once the vehicle's odometry has been still for `settle_s`, retried until the
EKF accepts it), take off; then wait for the landing
judge's result on /sim/landing, wait up to `autopilot_confirm_s` for the autopilot's own verdict
(/uav/landed_state ON_GROUND: ArduCopter's land detector declared the landing) and record it as
`autopilot_landed`, and make sure the vehicle is disarmed so the simulator starts the next episode
(LAND disarms on the ground). `LandingRunnerCore` is that sequence as a state machine driven by
`poll(now)`; the node (landing_runner.py) turns its requests into /uav/* service calls.
Times are seconds on a steady clock (the arm retries wait for the autopilot, not for sim time).
"""
from __future__ import annotations

import enum
import logging
import math
from dataclasses import dataclass, field

from assist_common.settings import check_named, setting

_LOG = logging.getLogger(__name__)


class RunnerState(enum.Enum):
    """Where the runner is in the current episode."""

    WAIT_EPISODE = 'wait_episode'   # waiting for a new /sim/goal (the next episode's scene)
    ARMING = 'arming'               # GUIDED + arm, retried while the autopilot refuses
    TAKING_OFF = 'taking_off'       # takeoff requested
    FLYING = 'flying'               # the pilot flies; waiting for the landing result
    CONFIRMING = 'confirming'       # landing result in; waiting for the autopilot's ON_GROUND before LAND
    DONE = 'done'                   # all episodes flown
    FAILED = 'failed'               # the autopilot kept refusing for arm_give_up_s


@dataclass
class RunnerConfig:
    """Settings of the episode sequence (the node's parameters)."""

    episodes: int = setting(0, ge=0)  # landings to fly; 0: until stopped
    arm_retry_s: float = setting(5.0, gt=0)  # wait this long after a refused arm / takeoff before retrying
    arm_give_up_s: float = setting(300.0, gt=0)  # fail when no arm + takeoff succeeded this long into an episode
    flight_timeout_s: float = setting(150.0, gt=0)  # no landing result this long after takeoff: request LAND
    land_after_touchdown: bool = True  # request LAND after the landing result (disarms on the ground)
    # still refused this long into an episode: reboot the autopilot once; 0: never
    reboot_after_s: float = setting(120.0, ge=0)
    reboot_after_crash: bool = False  # reboot before the episode after a crash (SITL's EKF may not survive one)
    # no next episode this long after the landing's LAND: force-disarm; 0: never
    disarm_timeout_s: float = setting(20.0, ge=0)
    # after a touchdown result, wait this long for ON_GROUND before LAND; 0: don't
    autopilot_confirm_s: float = setting(3.0, ge=0)
    # arm only once /odom has been still this long (speed <= settle_speed_mps, position within settle_drift_m):
    # an estimate still moving (SITL's EKF re-converging after the sim moved the vehicle to the next start
    # spot) would put the takeoff's ground, and the first metres of the approach, where the vehicle is not
    settle_s: float = setting(1.0, ge=0)  # 0: arm without waiting for the odometry
    settle_speed_mps: float = setting(0.05, gt=0)
    settle_drift_m: float = setting(0.05, gt=0)

    def __post_init__(self) -> None:
        """Reject settings outside their fields' ranges (SettingsError, one line)."""
        check_named(self)


# MAV_LANDED_STATE_ON_GROUND: the autopilot's land detector declared the vehicle landed
ON_GROUND = 1
# results with no touchdown for the autopilot to confirm (as the simulator's ArduCopter plant judges them)
AIR_CRASH_REASONS = ('tipped over', 'fell below the crash height')


def touched_down(result: dict) -> bool:
    """Whether a /sim/landing result is a touchdown the autopilot can confirm (not a timeout or a crash in the air)."""
    reason = str(result.get('reason') or '')
    return result.get('outcome') != 'timeout' and reason not in AIR_CRASH_REASONS and not reason.startswith('impact')


@dataclass
class RunnerStats:
    """Landing results seen so far (dicts as published on /sim/landing)."""

    results: list[dict] = field(default_factory=list)

    def summary(self) -> str:
        """One line: count, goal-pad success, crash rate, mean error."""
        n = len(self.results)
        if n == 0:
            return 'no landings'
        ok = sum(bool(r.get('success')) for r in self.results)
        crash = sum(bool(r.get('crash')) for r in self.results)
        errs = [float(r['error_m']) for r in self.results
                if isinstance(r.get('error_m'), (int, float)) and math.isfinite(float(r['error_m']))]
        mean = f'{sum(errs) / len(errs):.3f} m' if errs else 'n/a'
        text = (f'{n} landings: success {ok}/{n} ({100.0 * ok / n:.1f} %), crash {crash}/{n} '
                f'({100.0 * crash / n:.1f} %), mean error {mean}')
        verdicts = [r['autopilot_landed'] for r in self.results if isinstance(r.get('autopilot_landed'), bool)]
        if verdicts:
            text += f', autopilot landed {sum(verdicts)}/{len(verdicts)}'
        return text


class LandingRunnerCore:
    """GUIDED -> arm -> takeoff -> (pilot flies) -> landing result -> LAND, once per episode."""

    def __init__(self, cfg: RunnerConfig):
        self.cfg = cfg
        self.state = RunnerState.WAIT_EPISODE
        self.stats = RunnerStats()
        self.episode_started: float | None = None
        self._goal_key: object = None
        self._goal_pending = False
        self._queue: list[str] = []       # service calls still to make in this step of the sequence
        self._in_flight: str | None = None
        self._not_before = 0.0
        self._takeoff_at: float | None = None
        self._flight_land_sent = False
        self._rebooted = False
        self._reboot_next = False
        self._landed_at: float | None = None
        self._pending: dict | None = None           # a landing result waiting for the autopilot's verdict
        self._confirm_until = 0.0
        self._heard_landed_state = False           # the autopilot reported a landed state during this episode
        self.failure: str | None = None
        self._still_since: float | None = None      # /odom still (settle_*) since then, at _still_position
        self._still_position: tuple[float, float, float] | None = None
        self._last_odometry: float | None = None
        self._settle_logged = False

    # inputs -------------------------------------------------------------------------------------
    def on_goal(self, key: object, now: float) -> None:
        """A /sim/goal message; a key (stamp + point) not seen before announces a new episode."""
        if key == self._goal_key:
            return
        self._goal_key = key
        self._goal_pending = True

    def on_landing(self, result: dict, now: float) -> None:
        """A landing result from the judge: the episode is over once the autopilot's verdict is in.

        A touchdown waits up to autopilot_confirm_s for ON_GROUND (recorded as autopilot_landed true/false)
        before LAND is requested; a timeout, a crash in the air, autopilot_confirm_s 0 or an autopilot that
        reported no landed state this episode records '' (no verdict) and goes on at once."""
        if self._pending is not None:          # a second result before the verdict on the first
            self._record(self._pending, '', now)
        if self.state not in (RunnerState.FLYING, RunnerState.TAKING_OFF):
            _LOG.warning('landing result while %s (episode %s): recorded anyway', self.state.value,
                         result.get('episode'))
        self._reboot_next = self.cfg.reboot_after_crash and bool(result.get('crash'))
        self._takeoff_at = None
        self._goal_pending = False              # the next episode is announced by the next new goal
        self._queue = []
        if self.cfg.autopilot_confirm_s > 0 and self._heard_landed_state and touched_down(result):
            self._pending = dict(result)
            self._confirm_until = now + self.cfg.autopilot_confirm_s
            self.state = RunnerState.CONFIRMING
        else:
            self._record(result, '', now)

    def on_odometry(self, position, velocity, now: float) -> None:
        """An /odom sample (position in odom, velocity in any frame); non-finite samples are ignored."""
        pos = tuple(float(v) for v in position)
        speed = math.sqrt(sum(float(v) ** 2 for v in velocity))
        if not (all(math.isfinite(v) for v in pos) and math.isfinite(speed)):
            return
        self._last_odometry = now
        moved = (self._still_position is not None
                 and math.dist(pos, self._still_position) > self.cfg.settle_drift_m)
        if speed > self.cfg.settle_speed_mps or moved:
            self._still_since, self._still_position = None, None
        if self._still_since is None:
            self._still_since, self._still_position = now, pos

    def odometry_settled(self, now: float) -> bool:
        """Whether /odom has been still for settle_s, up to now (always true with settle_s 0)."""
        if self.cfg.settle_s <= 0:
            return True
        return (self._still_since is not None and self._last_odometry is not None
                and now - self._last_odometry <= self.cfg.settle_s
                and self._last_odometry - self._still_since >= self.cfg.settle_s)

    def on_landed_state(self, state: int, now: float) -> None:
        """A MAV_LANDED_STATE report from the autopilot (/uav/landed_state, at every report)."""
        self._heard_landed_state = True
        if self.state == RunnerState.CONFIRMING and int(state) == ON_GROUND:
            self._record(self._pending, now <= self._confirm_until, now)   # late (poll not run yet): not in time

    def flush(self, now: float) -> None:
        """Record a result still waiting for its verdict (the runner stops): autopilot_landed ''."""
        if self._pending is not None:
            self._record(self._pending, '', now)

    def _record(self, result: dict, autopilot_landed: bool | str, now: float) -> None:
        """Keep `result` with the autopilot's verdict, then LAND and the next episode (or done)."""
        self._pending = None
        result = dict(result, autopilot_landed=autopilot_landed)
        self.stats.results.append(result)
        _LOG.info('landing %d: %s, error %s m (%s), autopilot landed: %s', len(self.stats.results),
                  result.get('outcome'), _fmt(result.get('error_m')), result.get('reason'),
                  'n/a' if autopilot_landed == '' else ('yes' if autopilot_landed else
                                                        f'no ON_GROUND within {self.cfg.autopilot_confirm_s:.1f} s'))
        self._queue = ['land'] if self.cfg.land_after_touchdown else []
        self._landed_at = now
        if self.cfg.episodes and len(self.stats.results) >= self.cfg.episodes:
            self.state = RunnerState.DONE
            _LOG.info('all %d episodes flown: %s', self.cfg.episodes, self.stats.summary())
        else:
            self.state = RunnerState.WAIT_EPISODE

    def on_answer(self, name: str, success: bool, message: str, now: float) -> None:
        """The answer (or a timeout, success False) of the service call `poll` asked for."""
        if name != self._in_flight:
            _LOG.warning('answer to /uav/%s, which was not in flight (%s): ignored', name, self._in_flight)
            return
        self._in_flight = None
        if success:
            _LOG.info('/uav/%s: %s', name, message)
        if name == 'reboot':
            if not success:
                _LOG.warning('reboot refused (%s); arming goes on', message)
            self._not_before = now + self.cfg.arm_retry_s
        elif self.state == RunnerState.ARMING:
            if name == 'arm' and not success:
                _LOG.info('arm refused (%s); retrying in %.0f s', message, self.cfg.arm_retry_s)
                self._retry(now, ['guided', 'arm'])
            elif name == 'guided' and not success:
                _LOG.info('GUIDED refused (%s); retrying in %.0f s', message, self.cfg.arm_retry_s)
                self._retry(now, ['guided', 'arm'])
            elif name == 'arm' and not self._queue:
                self.state = RunnerState.TAKING_OFF
                self._queue = ['takeoff']
        elif self.state == RunnerState.TAKING_OFF and name == 'takeoff':
            if success:
                self.state = RunnerState.FLYING
                self._takeoff_at = now
                self._flight_land_sent = False
            else:                           # e.g. auto-disarmed meanwhile: arm again
                _LOG.info('takeoff refused (%s); arming again in %.0f s', message, self.cfg.arm_retry_s)
                self.state = RunnerState.ARMING
                self._retry(now, ['guided', 'arm'])
        elif not success:
            _LOG.warning('/uav/%s failed while %s: %s', name, self.state.value, message)

    # output -------------------------------------------------------------------------------------
    def poll(self, now: float) -> str | None:
        """The /uav/* service to call now (None: nothing to do); one call at a time."""
        if self.state == RunnerState.CONFIRMING and now >= self._confirm_until:
            self._record(self._pending, False, now)
        if self._in_flight is not None or self.state == RunnerState.FAILED:
            return None
        if self.state == RunnerState.WAIT_EPISODE and not self._goal_pending and self._landed_at is not None \
                and self.cfg.disarm_timeout_s > 0 and now - self._landed_at > self.cfg.disarm_timeout_s:
            # the sim starts the next episode once the motors stop: an autopilot that never detects
            # this landing (resting on a pad edge, on its side) never disarms by itself
            _LOG.warning('no new episode %.0f s after the landing: the vehicle did not disarm; force-disarming',
                         now - self._landed_at)
            self._landed_at = None
            self._queue = ['force_disarm']
        if self.state == RunnerState.WAIT_EPISODE and self._goal_pending and not self._queue:
            self._goal_pending = False
            self._landed_at = None
            self._heard_landed_state = False
            # still for settle_s from the announcement on: before it the vehicle rested where the last landing
            # ended, and the estimate starts sliding to the new start spot only once the sim has moved it there
            self._still_since, self._still_position = None, None
            self.state = RunnerState.ARMING
            self.episode_started = now
            self._rebooted = self._reboot_next
            self._queue = ['reboot', 'guided', 'arm'] if self._reboot_next else ['guided', 'arm']
            _LOG.info('episode %d: %s', len(self.stats.results) + 1,
                      'rebooting the autopilot after the crash, then arming' if self._reboot_next else 'arming')
            self._reboot_next = False
        if self.state == RunnerState.ARMING and self.episode_started is not None \
                and now - self.episode_started > self.cfg.arm_give_up_s:
            self.state = RunnerState.FAILED
            self.failure = (f'the autopilot did not arm and take off within {self.cfg.arm_give_up_s:.0f} s '
                            f'(episode {len(self.stats.results) + 1})')
            _LOG.error('%s', self.failure)
            return None
        if self.state == RunnerState.ARMING and self.cfg.reboot_after_s > 0 and not self._rebooted \
                and self.episode_started is not None and now - self.episode_started > self.cfg.reboot_after_s:
            # e.g. ArduCopter SITL's EKF after a crash flipped the airframe: it never re-converges
            _LOG.warning('the autopilot has refused to arm for %.0f s: rebooting it once',
                         now - self.episode_started)
            self._rebooted = True
            self._queue = ['reboot', 'guided', 'arm']
            self._not_before = now
        if self.state == RunnerState.FLYING and self._takeoff_at is not None and not self._flight_land_sent \
                and now - self._takeoff_at > self.cfg.flight_timeout_s:
            _LOG.warning('no landing result %.0f s after takeoff: requesting LAND', self.cfg.flight_timeout_s)
            self._flight_land_sent = True
            self._queue = ['land']
        if not self._queue or now < self._not_before:
            return None
        if self._queue[0] == 'arm' and not self.odometry_settled(now):
            if not self._settle_logged:
                _LOG.info('waiting for the odometry to settle (still for %.1f s) before arming', self.cfg.settle_s)
                self._settle_logged = True
            return None
        self._settle_logged = False
        self._in_flight = self._queue.pop(0)
        return self._in_flight

    @property
    def finished(self) -> bool:
        """True once all episodes are flown and the final LAND request is answered."""
        return self.state == RunnerState.DONE and not self._queue and self._in_flight is None

    def _retry(self, now: float, calls: list[str]) -> None:
        self._queue = list(calls)
        self._not_before = now + self.cfg.arm_retry_s


def _fmt(v: object) -> str:
    return f'{float(v):.3f}' if isinstance(v, (int, float)) else str(v)
