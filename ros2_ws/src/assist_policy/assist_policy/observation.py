"""Observation building for the assistant (paper, "TD3 implementation").

Each step the agent sees: a condition-specific scene feature, the vehicle dynamics, the pilot's
current action and the mean pilot and mean agent actions over the previous 1 s:

    obs = [feature..., v_x, v_y, v_z, z / Z_SCALE, u_x, u_y, u_z, mean_u (3), mean_a (3)]

feature per condition (``Condition``):
  latent      the CM-VAE encoder mean vector mu (its length is the encoder's latent size)
  oracle      the true goal relative to the vehicle, (G - p) / GOAL_SCALE, clipped (sim only)
  end_to_end  nothing in the vector; the raw 4x64x64 RGB-D image goes through a conv net

The vector part is the same for every condition, so one builder serves training, evaluation
and the policy node. Times are in seconds of whatever clock the caller uses (sim or ROS).

Feature memory (optional): an actor whose metadata lists ``feature_lags_s`` (e.g. [1, 2])
also sees the scene feature as it was that many seconds ago (``FeatureMemory``), appended after the
vector above, so it still knows where the pads were after they left the view. Actors without it
(every older file) see exactly the layout above. With ``memory_displacement`` the actor also sees,
after the lagged features, how far the vehicle has moved since each of them was seen
(p_now - p_then in the odometry frame, metres, 3 per lag): a lagged view of the pad is relative to
where the vehicle was then, and the displacement is what turns it into where the pad is now.

History window (optional): an actor whose metadata sets ``history_s`` (e.g. 4) also sees, after all of the
above, the flight's last ``history_s`` seconds sampled every ``history_step_s`` (``HistoryWindow``), oldest
first, one row per sample: [feature, v (3), z / Z_SCALE, u (3), the agent action applied (3), p_now - p_then
(3, clipped), valid (1)]. A learned memory (``actor.Actor``'s GRU) reads it, so persistent disagreement, pads seen
earlier and keys reversing are learned rather than written as rules. Rows from before the flight began (the
builder was reset at every flight boundary) or from a gap (no step within ``history_step_s`` before the row's time:
the actor did not run, inputs stalled) are zeros with valid = 0: memory never reaches across a boundary or
repeats a stale step.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from enum import Enum

import numpy as np

GOAL_SCALE = 4.0      # m; one pad spacing: oracle goal offsets become O(1)
GOAL_CLIP = 6.0       # after scaling; beyond ~24 m the exact offset no longer matters
Z_SCALE = 4.0         # m; start altitude is 3-4 m
DYNAMICS_DIM = 4      # v (3) + scaled altitude (1)
ACTIONS_DIM = 9       # u, mean u, mean a
DISPLACEMENT_DIM = 3  # per feature lag with memory displacement: p_now - p_then (m, odometry frame)
# m, per axis: a displacement is clipped to this. Training never sees more than ~2.2 m (2 s lag); an
# odometry jump (EKF reset, teleport without a new goal) reaches the actor bounded.
DISPLACEMENT_CLIP_M = 5.0
IMAGE_SHAPE = (4, 64, 64)  # end-to-end: RGB (0..1) + depth (m / DEPTH_SCALE)
DEPTH_SCALE = 5.0
TIME_EPS = 1e-6   # s; sample times closer than this count as equal


class Condition(str, Enum):
    """Which scene feature the assistant observes."""

    LATENT = 'latent'
    ORACLE = 'oracle'
    END_TO_END = 'end_to_end'

    @property
    def knows_goal(self) -> bool:
        """Told the goal (oracle, simulation only): the goal-agnostic rules (pilot override, pad recall,
        oscillation damper) only cost it, so policy_node, evaluate and replay_assist leave them off by default."""
        return self is Condition.ORACLE


class ActionHistory:
    """Time-stamped pilot and agent actions; means over the trailing window (default 1 s)."""

    def __init__(self, window_s: float = 1.0):
        if window_s <= 0:
            raise ValueError(f'window_s must be > 0, got {window_s}')
        self.window_s = float(window_s)
        self._items: deque[tuple[float, np.ndarray, np.ndarray]] = deque()
        # means() of the last `now` until the next push or clear: the observation and the pilot override
        # both ask for the same step's means
        self._means: tuple[float, np.ndarray, np.ndarray] | None = None

    def clear(self) -> None:
        """Forget every sample (new episode)."""
        self._items.clear()
        self._means = None

    def push(self, t: float, u: np.ndarray, a: np.ndarray) -> None:
        """Record the pilot action `u` and agent action `a` applied at time `t`."""
        u = np.asarray(u, dtype=float).reshape(3)
        a = np.asarray(a, dtype=float).reshape(3)
        if not (np.all(np.isfinite(u)) and np.all(np.isfinite(a))):
            raise ValueError('ActionHistory.push: non-finite action')
        if not np.isfinite(t):   # a NaN stamp would never be pruned: the history would grow for ever
            raise ValueError(f'ActionHistory.push: non-finite time {t!r}')
        if self._items and t < self._items[-1][0]:
            self.clear()  # clock jumped backwards (sim reset): old samples are meaningless
        self._items.append((float(t), u, a))
        self._means = None
        self._prune(t)

    def _prune(self, now: float) -> None:
        # TIME_EPS: a sample exactly window_s old leaves the window whichever clock gave the times (float
        # seconds in the env, integer ns in ROS and bags differ in the last bits)
        while self._items and self._items[0][0] <= now - self.window_s + TIME_EPS:
            self._items.popleft()

    def means(self, now: float) -> tuple[np.ndarray, np.ndarray]:
        """Mean pilot and mean agent action over (now - window_s, now]; zeros when empty."""
        if not np.isfinite(now):
            raise ValueError(f'ActionHistory.means: non-finite time {now!r}')
        if self._means is None or self._means[0] != now:
            self._prune(now)
            if self._items:
                mean_u = np.stack([it[1] for it in self._items]).mean(axis=0)
                mean_a = np.stack([it[2] for it in self._items]).mean(axis=0)
            else:
                mean_u, mean_a = np.zeros(3), np.zeros(3)
            self._means = (now, mean_u, mean_a)
        return self._means[1].copy(), self._means[2].copy()

    def __len__(self) -> int:
        return len(self._items)


MAX_FEATURE_LAGS = 8      # lagged copies of the feature an actor may ask for
MAX_FEATURE_LAG_S = 30.0  # s
MAX_HISTORY_STEPS = 200   # rows of a history window an actor may ask for
HISTORY_EXTRA_DIM = 14    # history row after the feature: v (3), z (1), u (3), applied a (3), displacement (3), valid


class FeatureMemory:
    """Time-stamped scene features; the feature as it was `lag` seconds ago, for each of `lags_s`.

    With `displacement`, each feature is stored with the vehicle position it was seen from, and
    `lagged` also returns the displacement since then (p_now - p_then, 3 per lag, after the features;
    each value clipped to +-DISPLACEMENT_CLIP_M).
    """

    def __init__(self, lags_s: tuple[float, ...] = (), displacement: bool = False):
        lags = tuple(float(x) for x in lags_s)
        if len(lags) > MAX_FEATURE_LAGS or any(not (0.0 < x <= MAX_FEATURE_LAG_S) for x in lags):
            raise ValueError(f'feature lags must be at most {MAX_FEATURE_LAGS} values in (0, {MAX_FEATURE_LAG_S:g}] s, '
                             f'got {list(lags_s)}')
        if displacement and not lags:
            raise ValueError('memory displacement needs feature lags')
        self.lags_s = lags
        self.displacement = bool(displacement)
        self._items: deque[tuple[float, np.ndarray, np.ndarray]] = deque()

    def clear(self) -> None:
        """Forget every feature (new episode)."""
        self._items.clear()

    def lagged(self, now: float, feature: np.ndarray, position: np.ndarray | None = None) -> np.ndarray:
        """Record `feature` (seen from `position`) at `now`; the features seen at now - lag (oldest known if
        none that old), concatenated, then (with displacement) p_now - p_then for each.

        Empty when no lags are configured. A clock that jumps backwards (sim reset) clears the memory.
        ValueError for a non-finite time or position, or no position when displacement is on.
        """
        if not self.lags_s:
            return np.zeros(0)
        if not np.isfinite(now):
            raise ValueError(f'FeatureMemory.lagged: non-finite time {now!r}')
        if self.displacement:
            if position is None:
                raise ValueError('FeatureMemory.lagged: memory displacement needs the vehicle position')
            pos = np.asarray(position, dtype=float).reshape(3).copy()
            if not np.all(np.isfinite(pos)):
                raise ValueError('FeatureMemory.lagged: non-finite position')
        else:
            pos = np.zeros(3)
        if self._items and now < self._items[-1][0]:
            self.clear()
        self._items.append((float(now), np.asarray(feature, dtype=float).reshape(-1).copy(), pos))
        horizon = now - max(self.lags_s) + TIME_EPS
        while len(self._items) > 1 and self._items[1][0] <= horizon:   # keep one sample at least max lag old
            self._items.popleft()
        chosen = []
        for lag in self.lags_s:
            target = now - lag + TIME_EPS
            item = self._items[0]
            for candidate in self._items:
                if candidate[0] > target:
                    break
                item = candidate
            chosen.append(item)
        out = [item[1] for item in chosen]
        if self.displacement:
            out += [np.clip(pos - item[2], -DISPLACEMENT_CLIP_M, DISPLACEMENT_CLIP_M) for item in chosen]
        return np.concatenate(out)


def history_steps(history_s: float, step_s: float) -> int:
    """Rows of a history window covering `history_s` seconds at one row per `step_s` (0 when history_s is 0)."""
    if history_s <= 0.0:
        return 0
    if step_s <= 0.0:
        raise ValueError(f'history step must be > 0 s, got {step_s!r}')
    steps = int(round(history_s / step_s))
    if not 1 <= steps <= MAX_HISTORY_STEPS:
        raise ValueError(f'a history of {history_s:g} s at {step_s:g} s per row has {steps} rows; '
                         f'1 to {MAX_HISTORY_STEPS} are allowed')
    return steps


class HistoryWindow:
    """The flight's recent steps, sampled every `step_s` over the last `history_s` seconds (module docstring).

    ``window`` records the step it is called for and returns the rows before it (oldest first, flattened);
    ``applied`` fills in the agent action applied at that step once the chain has run.
    """

    def __init__(self, feature_size: int, history_s: float = 0.0, step_s: float = 0.25):
        self.steps = history_steps(history_s, step_s)
        self.step_s = float(step_s)
        self.feature_size = int(feature_size)
        self.row_dim = self.feature_size + HISTORY_EXTRA_DIM
        self._items: deque[tuple[float, np.ndarray, np.ndarray]] = deque()   # (t, row without displacement, p)

    def clear(self) -> None:
        """Forget every step (new episode or flight boundary)."""
        self._items.clear()

    def window(self, now: float, feature: np.ndarray, velocity: np.ndarray, altitude: float, u: np.ndarray,
               position: np.ndarray | None) -> np.ndarray:
        """Record this step and return the `steps` rows sampled at now - k * step_s, k = steps..1 (float32).

        A row is the latest step recorded at or before its sample time and less than `step_s` before it; none
        (the flight is younger, or a gap: the actor did not run, inputs stalled) gives a zero row with valid = 0,
        never an older step. A clock that jumps backwards clears the window first.
        ValueError for a non-finite time or position.
        """
        if not self.steps:
            return np.zeros(0, np.float32)
        if not np.isfinite(now):
            raise ValueError(f'HistoryWindow.window: non-finite time {now!r}')
        pos = np.zeros(3) if position is None else np.asarray(position, dtype=float).reshape(3)
        if not np.all(np.isfinite(pos)):
            raise ValueError('HistoryWindow.window: non-finite position')
        if self._items and now < self._items[-1][0]:
            self.clear()
        out = np.zeros((self.steps, self.row_dim), np.float32)
        targets = [now - k * self.step_s + TIME_EPS for k in range(self.steps, 0, -1)]
        items = list(self._items)
        j = -1
        for i, target in enumerate(targets):
            while j + 1 < len(items) and items[j + 1][0] <= target:
                j += 1
            if j < 0 or target - items[j][0] >= self.step_s:
                continue
            _, row, then = items[j]
            out[i, :row.size] = row
            out[i, row.size:row.size + 3] = np.clip(pos - then, -DISPLACEMENT_CLIP_M, DISPLACEMENT_CLIP_M)
            out[i, -1] = 1.0
        row = np.concatenate([np.asarray(feature, dtype=float).reshape(-1),
                              np.asarray(velocity, dtype=float).reshape(3), [float(altitude) / Z_SCALE],
                              np.asarray(u, dtype=float).reshape(3), np.zeros(3)])
        self._items.append((float(now), row, pos.copy()))
        horizon = now - self.steps * self.step_s + TIME_EPS
        while len(self._items) > 1 and self._items[1][0] <= horizon:     # keep one step at least a window old
            self._items.popleft()
        return out.reshape(-1)

    def applied(self, now: float, a: np.ndarray) -> None:
        """The agent action applied at the step recorded at `now` (ignored when no step was recorded then)."""
        if self._items and abs(self._items[-1][0] - now) <= TIME_EPS:
            self._items[-1][1][-3:] = np.asarray(a, dtype=float).reshape(3)


def feature_dim(condition: Condition | str, latent_dim: int = 0) -> int:
    """Length of the condition-specific part of the vector observation."""
    condition = Condition(condition)
    if condition is Condition.LATENT:
        if latent_dim <= 0:
            raise ValueError('latent condition needs latent_dim > 0')
        return latent_dim
    if condition is Condition.ORACLE:
        return 3
    return 0


def vector_dim(condition: Condition | str, latent_dim: int = 0, n_lags: int = 0,
               displacement: bool = False, n_history: int = 0) -> int:
    """Length of the full vector observation for `condition` (with `n_lags` lagged copies of the feature,
    with `displacement` the vehicle's displacement since each, and `n_history` history rows)."""
    feat = feature_dim(condition, latent_dim)
    return (feat * (1 + n_lags) + DYNAMICS_DIM + ACTIONS_DIM + (DISPLACEMENT_DIM * n_lags if displacement else 0)
            + n_history * (feat + HISTORY_EXTRA_DIM))


def oracle_feature(goal: np.ndarray, position: np.ndarray) -> np.ndarray:
    """True goal relative to the vehicle, scaled and clipped (oracle condition)."""
    rel = (np.asarray(goal, dtype=float).reshape(3) - np.asarray(position, dtype=float).reshape(3))
    return np.clip(rel / GOAL_SCALE, -GOAL_CLIP, GOAL_CLIP)


def image_feature(rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """RGB uint8 HxWx3 + depth float metres HxW -> float32 (4, H, W) for the end-to-end net."""
    rgb = np.asarray(rgb)
    depth = np.asarray(depth, dtype=np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3 or depth.shape != rgb.shape[:2]:
        raise ValueError(f'image_feature: bad shapes rgb {rgb.shape} depth {depth.shape}')
    d = np.where(np.isfinite(depth), depth, 0.0) / DEPTH_SCALE
    img = np.concatenate([rgb.astype(np.float32).transpose(2, 0, 1) / 255.0, d[None]], axis=0)
    return img.astype(np.float32)


def build_vector(feature: np.ndarray, velocity: np.ndarray, altitude: float, u: np.ndarray,
                 mean_u: np.ndarray, mean_a: np.ndarray) -> np.ndarray:
    """Concatenate the parts of the vector observation (float32); ValueError if non-finite."""
    parts = [np.asarray(feature, dtype=float).reshape(-1),
             np.asarray(velocity, dtype=float).reshape(3),
             np.array([float(altitude) / Z_SCALE]),
             np.asarray(u, dtype=float).reshape(3),
             np.asarray(mean_u, dtype=float).reshape(3),
             np.asarray(mean_a, dtype=float).reshape(3)]
    obs = np.concatenate(parts).astype(np.float32)
    if not np.all(np.isfinite(obs)):
        raise ValueError('observation contains non-finite values')
    return obs


@dataclass
class ObservationBuilder:
    """Stateful builder: keeps the 1 s action history and assembles observations."""

    condition: Condition = Condition.ORACLE
    latent_dim: int = 0
    window_s: float = 1.0
    feature_lags_s: tuple[float, ...] = ()
    memory_displacement: bool = False
    history_s: float = 0.0          # history window (HistoryWindow); 0 = none
    history_step_s: float = 0.25

    def __post_init__(self) -> None:
        self.condition = Condition(self.condition)
        if (self.feature_lags_s or self.history_s > 0) and self.condition is Condition.END_TO_END:
            raise ValueError('feature lags and a history window need a vector feature (latent or oracle), '
                             'not end_to_end')
        self.history = ActionHistory(self.window_s)
        self.memory = FeatureMemory(tuple(self.feature_lags_s), bool(self.memory_displacement))
        feat = feature_dim(self.condition, self.latent_dim)
        self.window = HistoryWindow(feat, float(self.history_s), float(self.history_step_s))
        self.dim = vector_dim(self.condition, self.latent_dim, len(self.memory.lags_s), self.memory.displacement,
                              self.window.steps)

    @classmethod
    def for_actor(cls, condition: Condition | str, meta: dict) -> ObservationBuilder:
        """The builder an actor's (validated) metadata declares, for `condition`."""
        return cls(Condition(condition), int(meta['latent_dim']), float(meta['window_s']),
                   tuple(meta['feature_lags_s']), bool(meta['memory_displacement']), float(meta['history_s']),
                   float(meta['history_step_s']))

    def reset(self) -> None:
        """Start a new episode."""
        self.history.clear()
        self.memory.clear()
        self.window.clear()

    def build(self, now: float, feature: np.ndarray, velocity: np.ndarray, altitude: float,
              u: np.ndarray, position: np.ndarray | None = None) -> np.ndarray:
        """Observation at time `now` from the feature, dynamics and current pilot action (`position`, the
        odometry position, is needed with memory displacement only)."""
        feature = np.asarray(feature, dtype=float).reshape(-1)
        expected = feature_dim(self.condition, self.latent_dim)
        if feature.size != expected:
            raise ValueError(f'{self.condition.value} feature has {feature.size} values, expected {expected}')
        mean_u, mean_a = self.history.means(now)
        obs = build_vector(feature, velocity, altitude, u, mean_u, mean_a)
        if not (self.memory.lags_s or self.window.steps):
            return obs
        return np.concatenate([obs, self.memory.lagged(now, feature, position).astype(np.float32),
                               self.window.window(now, feature, velocity, altitude, u, position)])

    def record(self, now: float, u: np.ndarray, a: np.ndarray) -> None:
        """Remember the pilot action and agent action applied at time `now`."""
        self.history.push(now, u, a)
        self.window.applied(now, a)
