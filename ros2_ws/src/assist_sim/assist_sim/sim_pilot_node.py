"""sim_pilot_node: the simulated pilot (assist_sim.pilot) as a ROS 2 node publishing /pilot/cmd_vel.

Reads /odom, the latched /sim/goal (every message starts a new landing: a fresh goal estimate) and
/assist/agent_cmd (the assistant's action, which pulls the pilot's estimate with conformance alpha
while it is above the blending threshold and fresh). `pilot` picks the model: `paper` (the reference)
or a family / population of assist_sim.pilots (a fresh pilot, with freshly drawn family parameters,
for every landing; the pad positions for the wrong-pad family come from the latched /sim/scene).

An evaluation plan (`episode_seeds`, with `episode_betas` and `episode_pilots`, one entry per landing in
order: landing i is the i-th /sim/goal this node receives) makes landing i's pilot exactly the
evaluation env's: a fresh ``make_pilot(episode_pilots[i], alpha, episode_betas[i], cfg,
np.random.default_rng(episode_seeds[i]), pads)``, started only once the latched /sim/scene of that
landing (the one whose pads hold the goal) is in. Past the end of the plan (or without one) the
landings follow `pilot`, `beta` and `seed` as before.

Cues (`cue_trust` > 0): the pilot reads the assistant's intent as the pilot station shows it (assist_sim.cues):
/assist/goal_estimate (the highlighted pad, its xy standard deviation from the covariance) and /assist/descent_ok
(the light), each while no older than `cue_timeout_s` and only while the assistant acts (/assist/agent_cmd fresh),
as the station never shows a cue with the assistance off. A malformed estimate (non-finite, a negative variance)
is not read and is counted (rejected_goal_estimate).
"""
from __future__ import annotations

import threading

import numpy as np
import math

from geometry_msgs.msg import PointStamped, PoseWithCovarianceStamped, TwistStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.node import Node
from std_msgs.msg import Bool
from visualization_msgs.msg import MarkerArray

from assist_common.ros_io import (LATCHED_QOS, RELIABLE_QOS, SENSOR_QOS, Diagnostics, fill_twist, forward_logging,
                                  twist_to_array)
from assist_common.ros_params import Param, StartupError, declare_parameters
from assist_common.ros_run import exit_process, run_node

from .cues import Cue, CueConfig
from .pilot import PilotConfig
from .pilots import GRAPH_PILOT_NAMES, make_pilot

PARAMS = {
    'alpha': Param(0.5, 'Conformance to the assistant in [0, 1] (paper alpha; settable at run time).',
                   min=0.0, max=1.0, dynamic=True),
    'beta': Param(0.5, 'Skill in [0, 1]: how fast the pilot fixes its goal estimate (paper beta; settable at '
                       'run time).', min=0.0, max=1.0, dynamic=True),
    'seed': Param(0, 'Randomness of the pilot (initial estimates, perception errors).', min=0, max=2**31 - 1),
    'rate_hz': Param(20.0, 'Command rate (the pilot model is calibrated at 20 Hz).', min=1.0, max=200.0),
    'blend_threshold': Param(0.25, 'Assistant actions at or below this norm (m/s) are not felt by the pilot '
                                   '(settable at run time).', min=0.0, max=10.0, dynamic=True),
    'agent_timeout_s': Param(0.5, '/assist/agent_cmd older than this counts as absent (settable at run time).',
                             min=0.0, max=10.0, min_exclusive=True, dynamic=True),
    'odom_timeout_s': Param(0.5, 'With /odom older than this the pilot sends zero velocity (settable at run '
                                 'time).', min=0.0, max=10.0, min_exclusive=True, dynamic=True),
    'pilot': Param('paper', 'Pilot model: paper (the reference) or an assist_sim.pilots family or population '
                            '(mix = held-out families, train_mix = training families), drawn anew per landing.',
                   choices=GRAPH_PILOT_NAMES),
    'episode_seeds': Param((), 'Evaluation plan: seed of the pilot of landing 0, 1, 2, ... (each its own fresh pilot, '
                               'as the evaluation env builds it); empty: the landings follow seed.', min=0,
                           max=2**31 - 1, item_type=int),
    'episode_betas': Param((), 'Evaluation plan: skill of the pilot of landing 0, 1, 2, ... (needs episode_seeds, '
                               'same length); empty: beta.', min=0.0, max=1.0, item_type=float),
    'episode_pilots': Param((), 'Evaluation plan: pilot model (family or population, drawn with that landing\'s '
                                'seed) of landing 0, 1, 2, ... (needs episode_seeds, same length); empty: pilot.',
                            choices=GRAPH_PILOT_NAMES, item_type=str),
    'frame_id': Param('base_link', 'frame_id of /pilot/cmd_vel.'),
    'cue_trust': Param(0.0, "Chance per landing that the pilot reads the assistant's cues (/assist/goal_estimate, "
                            '/assist/descent_ok; assist_sim.cues); 0: it never looks at them.', min=0.0, max=1.0),
    'cue_timeout_s': Param(0.5, 'A cue older than this is not shown (the station greys it).', min=0.0, max=10.0,
                           min_exclusive=True, dynamic=True),
    'start_altitude_m': Param(0.0, 'A landing starts (the pilot model is reset to the new goal) once /odom is at '
                                   'or above this altitude; 0: at once. For episodes that start on the ground '
                                   '(ArduPilot SITL, MAVLink vehicles) set it just below the takeoff altitude '
                                   'so the pilot does not spend the arming wait on the ground.',
                               min=0.0, max=100.0),
}


class SimPilotNode(Node):
    """Keyboard-like simulated pilot flying toward its (wrong, improving) goal estimate."""

    def __init__(self, **kwargs):
        super().__init__('sim_pilot_node', **kwargs)
        forward_logging(self)
        self._lock = threading.Lock()
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params)
        self.diag = Diagnostics(self)
        cfg = PilotConfig(control_hz=float(self.p['rate_hz']), k_alpha=float(self.p['rate_hz']))
        self._cfg = cfg
        self._rng = np.random.default_rng(int(self.p['seed']))
        self._pads: np.ndarray | None = None
        n_plan = len(self.p['episode_seeds'])
        for key in ('episode_betas', 'episode_pilots'):
            if self.p[key] and len(self.p[key]) != n_plan:
                raise StartupError(f"sim_pilot_node: {key} has {len(self.p[key])} entries, episode_seeds {n_plan}: "
                                   'an evaluation plan gives every landing its seed (and beta, pilot)')
        self._cue_cfg = CueConfig(trust=float(self.p['cue_trust'])) if self.p['cue_trust'] > 0 else None
        self.pilot = self._new_pilot()
        self._default_pilot = self.pilot        # the paper pilot flies every landing past the plan
        self._odom: tuple[float, np.ndarray] | None = None
        self._agent: tuple[float, np.ndarray] | None = None
        self._pending_goal: np.ndarray | None = None
        self._active = False
        self.episodes = 0
        group = MutuallyExclusiveCallbackGroup()
        self.pub = self.create_publisher(TwistStamped, '/pilot/cmd_vel', RELIABLE_QOS)
        self.create_subscription(Odometry, '/odom', self._on_odom, SENSOR_QOS, callback_group=group)
        self.create_subscription(PointStamped, '/sim/goal', self._on_goal, LATCHED_QOS, callback_group=group)
        self.create_subscription(TwistStamped, '/assist/agent_cmd', self._on_agent, RELIABLE_QOS,
                                 callback_group=group)
        self.create_subscription(MarkerArray, '/sim/scene', self._on_scene, LATCHED_QOS, callback_group=group)
        self._goal_cue: tuple[float, np.ndarray, float] | None = None     # (arrival, pad top centre, xy std)
        self._light: tuple[float, bool] | None = None
        if self._cue_cfg is not None:
            self.create_subscription(PoseWithCovarianceStamped, '/assist/goal_estimate', self._on_goal_estimate,
                                     RELIABLE_QOS, callback_group=group)
            self.create_subscription(Bool, '/assist/descent_ok', self._on_descent_ok, RELIABLE_QOS,
                                     callback_group=group)
        self.create_timer(1.0 / float(self.p['rate_hz']), self._tick, callback_group=group)
        self.get_logger().info(f"sim_pilot_node: pilot {self.p['pilot']} alpha {self.p['alpha']} "
                               f"beta {self.p['beta']} seed {self.p['seed']}")

    def _new_pilot(self):
        return make_pilot(self.p['pilot'], float(self.p['alpha']), float(self.p['beta']), self._cfg, self._rng,
                          pads=self._pads, cues=self._cue_cfg)

    def _planned_pilot(self, i: int):
        """Landing i's pilot from the evaluation plan (the env's: its own generator seeded per landing)."""
        pilots, betas = self.p['episode_pilots'], self.p['episode_betas']
        return make_pilot(pilots[i] if pilots else self.p['pilot'], float(self.p['alpha']),
                          float(betas[i]) if betas else float(self.p['beta']), self._cfg,
                          np.random.default_rng(int(self.p['episode_seeds'][i])), pads=self._pads, cues=self._cue_cfg)

    def _scene_holds(self, goal: np.ndarray) -> bool:
        """True when the latest /sim/scene is the scene of `goal` (one of its pad tops is the goal)."""
        return self._pads is not None and bool(np.any(np.linalg.norm(self._pads - goal, axis=1) < 1e-3))

    def _on_scene(self, msg: MarkerArray) -> None:
        tops = {m.id: (m.pose.position.x, m.pose.position.y, m.pose.position.z + 0.5 * m.scale.z)
                for m in msg.markers if m.ns == 'platforms'}
        pads = np.array([tops[k] for k in sorted(tops)], dtype=float).reshape(-1, 3)
        if pads.size == 0 or not np.all(np.isfinite(pads)):
            self.diag.count('rejected_scene')
            self.get_logger().warning('rejected /sim/scene without finite platforms')
            return
        with self._lock:
            self._pads = pads

    def _on_params(self, changed: dict) -> None:
        """alpha / beta go to the pilot model; the thresholds and timeouts are read every tick."""
        with self._lock:
            for pilot in {id(p): p for p in (self.pilot, self._default_pilot)}.values():
                if 'alpha' in changed:
                    pilot.alpha = pilot.base_alpha = float(changed['alpha'])
                if 'beta' in changed:
                    pilot.beta = float(changed['beta'])

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_odom(self, msg: Odometry) -> None:
        p = msg.pose.pose.position
        pos = np.array([p.x, p.y, p.z])
        if not np.all(np.isfinite(pos)):
            self.diag.count('rejected_odom')
            self.get_logger().warning('rejected non-finite odometry', throttle_duration_sec=2.0)
            return
        with self._lock:
            self._odom = (self._now(), pos)

    def _on_goal(self, msg: PointStamped) -> None:
        g = np.array([msg.point.x, msg.point.y, msg.point.z])
        if not np.all(np.isfinite(g)):
            self.diag.count('rejected_goal')
            self.get_logger().warning('rejected non-finite goal')
            return
        with self._lock:
            self._pending_goal = g
            self._active = False        # no commands for the previous landing while this one waits to start

    def _on_agent(self, msg: TwistStamped) -> None:
        a = twist_to_array(msg)
        if not np.all(np.isfinite(a)):
            self.diag.count('rejected_agent')
            self.get_logger().warning('rejected non-finite agent command', throttle_duration_sec=2.0)
            return
        with self._lock:
            self._agent = (self._now(), a)

    def _on_goal_estimate(self, msg: PoseWithCovarianceStamped) -> None:
        p, cov = msg.pose.pose.position, np.asarray(msg.pose.covariance, dtype=float)
        goal = np.array([p.x, p.y, p.z])
        if cov.size != 36 or not (np.all(np.isfinite(goal)) and np.all(np.isfinite(cov[[0, 7]]))
                                  and cov[0] >= 0 and cov[7] >= 0):
            self.diag.count('rejected_goal_estimate')
            self.get_logger().warning('rejected a goal estimate that is not finite or has a negative variance',
                                      throttle_duration_sec=2.0)
            return
        with self._lock:
            self._goal_cue = (self._now(), goal, math.sqrt(max(cov[0], cov[7])))

    def _on_descent_ok(self, msg: Bool) -> None:
        with self._lock:
            self._light = (self._now(), bool(msg.data))

    def _cue(self, now: float, assisting: bool) -> Cue | None:
        """The cue the station would show now: fresh parts only, none while the assistant does not act."""
        timeout = float(self.p['cue_timeout_s'])
        if not assisting:
            return None
        goal = self._goal_cue if self._goal_cue is not None and abs(now - self._goal_cue[0]) <= timeout else None
        light = self._light if self._light is not None and abs(now - self._light[0]) <= timeout else None
        return Cue(None if goal is None else goal[1], math.inf if goal is None else goal[2],
                   None if light is None else light[1])

    def _tick(self) -> None:
        now = self._now()
        with self._lock:
            odom_ok = self._odom is not None and abs(now - self._odom[0]) <= self.p['odom_timeout_s']
            planned = self.episodes < len(self.p['episode_seeds'])
            if planned and self._pending_goal is not None and not self._scene_holds(self._pending_goal):
                self.get_logger().info('waiting for the /sim/scene of the new goal', throttle_duration_sec=2.0)
            elif self._pending_goal is not None and self._odom is not None \
                    and self._odom[1][2] >= self.p['start_altitude_m']:
                if planned:
                    self.pilot = self._planned_pilot(self.episodes)
                elif self.p['pilot'] != 'paper':
                    self.pilot = self._new_pilot()      # new family draw (and pads) per landing
                else:
                    self.pilot = self._default_pilot
                self.pilot.reset(self._pending_goal, self._odom[1])
                self.diag.set('pilot', self.pilot.name)
                self._pending_goal = None
                self._active = True
                self.episodes += 1
                self.diag.set('episodes', self.episodes)
                self.diag.set('goal_estimate', np.round(self.pilot.goal_estimate, 2).tolist())
            if not (odom_ok and self._active):
                u = np.zeros(3)
            else:
                a = None
                fresh = self._agent is not None and abs(now - self._agent[0]) <= self.p['agent_timeout_s']
                if fresh and float(np.linalg.norm(self._agent[1])) > self.p['blend_threshold']:
                    a = self._agent[1]
                if self._cue_cfg is not None:
                    self.pilot.see_cue(self._cue(now, fresh))
                u = self.pilot.act(self._odom[1], a)
        msg = TwistStamped()
        msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.p['frame_id']
        self.pub.publish(fill_twist(msg, u))


def main(args=None):
    """Console entry point."""
    exit_process(run_node(lambda: SimPilotNode(), args, params=PARAMS))


if __name__ == '__main__':
    main()
