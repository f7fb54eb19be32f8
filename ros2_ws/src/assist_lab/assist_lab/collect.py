"""Training landings flown by N env workers (local processes or Ray actors), the learner in the caller's process.

train_td3's phases that fly landings (demonstrations, DAgger rounds, TD3 collection and the periodic
evaluation) hand them to a `LandingPool` when it runs with more than one worker: each landing is a
`LandingTask` keyed by its episode number and seeds, flown by a `LandingWorker` that holds its own
environment (the run's EnvConfig), its own demonstrator and a copy of the actor whose weights come with
the task (`ActorWeights`). Results are taken in episode order, so a run is a deterministic function of
its seed and its worker count. With one worker nothing here starts: the landings are flown in the
learner's process exactly as they always have been (the same functions, `fly_demo` and
`evaluate_agent`'s run_episode).

What more than one worker changes, and what it does not:
- noise-free collection (DAgger rounds, noise-free demonstrations) and evaluation give the transitions and
  results of one worker, in the same order;
- demonstrations with noise draw each landing's noise from its own generator (seed, episode) instead of
  one stream across the landings: the same kind of data, other draws;
- TD3: a landing flies the actor's weights as they were when it was dispatched, up to N-1 landings
  behind the learner (the distributed-actor scheme of Ape-X and D4PG), its Ornstein-Uhlenbeck noise from
  its own generator at the scale of its landing number; a landing dispatched before `start_steps`
  flies uniformly random actions all through; the learner makes its `updates_per_step` updates per
  step when the landing's transitions arrive. The landing that crosses `total_steps` is the last one
  used; landings still in flight then are dropped.
"""
from __future__ import annotations

import functools
import itertools
import logging
import sys
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np
import torch
from tqdm import tqdm

from assist_perception.latent import make_latent_fn
from assist_policy.actor import build_actor, validate_actor_meta
from assist_policy.scripted import LEAD_S, NEAREST_PAD_VARIANTS, ScriptedConfig, ScriptedOracle, make_nearest_pad
from .cluster import WorkerPool
from .env import EnvConfig, LandingAssistEnv, run_episode
from .td3 import OUNoise, ReplayBuffer

log = logging.getLogger(__name__)

DEMO_POLICIES = ('oracle', 'oracle_lead', *NEAREST_PAD_VARIANTS, 'init_actor')
_VERSIONS = itertools.count(1)


def make_env(env_cfg: EnvConfig) -> LandingAssistEnv:
    """Env for a config, with the CM-VAE encoder attached for the latent condition."""
    if env_cfg.condition == 'latent':
        latent_fn, dim = make_latent_fn(env_cfg.encoder_path or None)
        env_cfg.latent_dim = dim
        return LandingAssistEnv(env_cfg, latent_fn=latent_fn)
    return LandingAssistEnv(env_cfg)


def demonstrator(demo_policy: str, max_speed) -> ScriptedOracle | None:
    """The scripted demonstrator `demo_policy` names (None for init_actor: the actor labels); ValueError if unknown."""
    if demo_policy not in DEMO_POLICIES:
        raise ValueError(f'demo_policy must be one of {", ".join(DEMO_POLICIES)}, got {demo_policy!r}')
    if demo_policy == 'init_actor':
        return None
    if demo_policy == 'oracle':
        return ScriptedOracle(max_speed=max_speed)
    if demo_policy == 'oracle_lead':
        return ScriptedOracle(ScriptedConfig(lead_s=LEAD_S), max_speed=max_speed)
    return make_nearest_pad(demo_policy, max_speed=max_speed)


@dataclass(frozen=True)
class ActorWeights:
    """A snapshot of the learner's actor that a worker can fly (`version` names the snapshot).

    The weights travel as numpy arrays, pickled by value: torch tensors would cross to a worker
    process as shared-memory file descriptors, whose hand-over a worker killed mid-way turns into a
    traceback from multiprocessing's resource-sharer thread in the learner.
    """

    meta: dict
    state: dict
    version: int

    @classmethod
    def of(cls, actor: torch.nn.Module, meta: dict) -> ActorWeights:
        """Snapshot `actor` (its architecture in `meta`, as TD3.meta holds it)."""
        return cls(dict(meta), {k: v.detach().cpu().numpy().copy() for k, v in actor.state_dict().items()},
                   next(_VERSIONS))

    def policy(self) -> Callable[[np.ndarray], np.ndarray]:
        """obs -> deterministic raw action, computed as TD3.act computes it on the CPU."""
        actor = build_actor(validate_actor_meta(dict(self.meta)))
        actor.load_state_dict({k: torch.from_numpy(v) for k, v in self.state.items()})
        actor.eval()

        @torch.no_grad()
        def act(obs: np.ndarray) -> np.ndarray:
            x = torch.as_tensor(np.asarray(obs, dtype=np.float32)).unsqueeze(0)
            return actor(x)[0].numpy().astype(float)
        return act


@dataclass(frozen=True)
class LandingTask:
    """One landing to fly. kind: 'demo' (a demonstrator or the actor flies, the demonstrator or the actor
    labels), 'td3' (the actor plus exploration noise, or random actions) or 'eval' (the actor, no noise)."""

    kind: str
    episode: int                         # its number in the phase: results are taken in this order
    seed: int                            # env.reset seed
    noise_seed: tuple[int, ...] = ()     # the landing's own noise generator
    noise: float = 0.0                   # demo: Gaussian noise (raw action units) on the flown action
    actor_flies: bool = False            # demo: the actor flies, the demonstrator labels (DAgger)
    actor_labels: bool = False           # demo: the actor labels (demo_policy init_actor)
    random_actions: bool = False         # td3: uniformly random actions
    ou: tuple[float, ...] = ()           # td3: OUNoise (theta, sigma, sigma_min, decay) and its landing number
    beta: float = 0.0                    # eval: the pilot's beta
    goal_labels: bool = False            # demo: each label also carries the true goal (env.goal_label)


@dataclass
class FlownLanding:
    """A flown landing: its transitions (done = terminated or truncated, as the buffer stores it) with the
    privileged values of each observation (env.privileged, for an asymmetric critic), the demonstrator's labels
    (demo) and the env's result."""

    episode: int
    obs: np.ndarray
    act: np.ndarray
    rew: np.ndarray
    next_obs: np.ndarray
    done: np.ndarray
    labels: np.ndarray | None
    result: dict
    beta: float
    episode_return: float
    active_steps: int
    priv: np.ndarray
    next_priv: np.ndarray

    @property
    def steps(self) -> int:
        """Transitions in the landing."""
        return len(self.act)

    def into(self, buffer: ReplayBuffer) -> None:
        """Append the transitions to `buffer` (with their privileged values when it keeps them)."""
        if buffer.priv_dim:
            buffer.extend(self.obs, self.act, self.rew, self.next_obs, self.done, self.priv, self.next_priv)
        else:
            buffer.extend(self.obs, self.act, self.rew, self.next_obs, self.done)


def _landing(env: LandingAssistEnv, seed: int, episode: int, choose: Callable[[np.ndarray], tuple]) -> FlownLanding:
    """Fly one landing from `env.reset(seed)`; `choose(obs)` -> (flown action, label or None)."""
    obs, info = env.reset(seed=seed)
    priv = env.privileged()
    rows: list[tuple] = []
    labels: list = []
    active = 0
    while True:
        act, label = choose(obs)
        nxt, rew, term, trunc, sinfo = env.step(act)
        nxt_priv = env.privileged()
        rows.append((obs, act, rew, nxt, term or trunc, priv, nxt_priv))
        labels.append(label)
        active += int(sinfo['active'])
        obs, priv = nxt, nxt_priv
        if term or trunc:
            break
    obs_a, act_a, rew_a, nxt_a, done_a, priv_a, nxt_priv_a = (np.asarray(col, np.float32) for col in zip(*rows))
    return FlownLanding(episode, obs_a, act_a, rew_a, nxt_a, done_a,
                        None if labels[0] is None else np.asarray(labels, np.float32), dict(sinfo['result']),
                        float(info['beta']), float(env.episode_return), active, priv_a, nxt_priv_a)


def fly_demo(env: LandingAssistEnv, seed: int, episode: int, rng: np.random.Generator, noise: float,
             script: ScriptedOracle | None, label_fn=None, act_fn=None, goal_labels: bool = False) -> FlownLanding:
    """A demonstration landing: every state labelled by `script` (or `label_fn(obs)` when script is None),
    followed by the true goal with `goal_labels`; flown by the label (+ Gaussian `noise` from `rng`) unless
    `act_fn(obs)` flies (DAgger)."""
    def choose(obs: np.ndarray) -> tuple:
        clean = np.asarray(label_fn(obs), dtype=float) if script is None else script.raw_action(env)
        flown = clean if act_fn is None else np.asarray(act_fn(obs), dtype=float)
        label = np.concatenate([clean, env.goal_label()]) if goal_labels else clean
        return np.clip(flown + rng.normal(0.0, noise, 3), -1.0, 1.0), label
    return _landing(env, seed, episode, choose)


def fly_td3(env: LandingAssistEnv, task: LandingTask, act_fn) -> FlownLanding:
    """A TD3 collection landing: random actions, or the actor plus Ornstein-Uhlenbeck noise (task.ou)."""
    rng = np.random.default_rng(task.noise_seed)
    if task.random_actions:
        def choose(obs: np.ndarray) -> tuple:
            return rng.uniform(-1.0, 1.0, 3), None
    else:
        theta, sigma, sigma_min, decay, landings = task.ou
        noise = OUNoise(3, theta, sigma, sigma_min, decay, rng=rng)
        noise.landings = int(landings)

        def choose(obs: np.ndarray) -> tuple:
            return np.clip(act_fn(obs) + noise.sample(), -1.0, 1.0), None
    return _landing(env, task.seed, task.episode, choose)


class LandingWorker:
    """Flies LandingTasks in its own environment (a worker process, a Ray actor or, in tests, in-process)."""

    def __init__(self, env_cfg: EnvConfig, demo_policy: str, torch_threads: int = 1) -> None:
        torch.set_num_threads(torch_threads)
        self.env = make_env(env_cfg)
        self.script = demonstrator(demo_policy, self.env.cfg.max_speed)
        self._policy: tuple[int, Callable | None] = (0, None)

    def _act_fn(self, weights: ActorWeights | None) -> Callable | None:
        if weights is None:
            return None
        if self._policy[0] != weights.version:
            self._policy = (weights.version, weights.policy())
        return self._policy[1]

    def fly(self, task: LandingTask, weights: ActorWeights | None) -> FlownLanding | dict:
        """The landing `task` names: a FlownLanding ('demo', 'td3') or run_episode's summary ('eval')."""
        act_fn = self._act_fn(weights)
        if task.kind == 'demo':
            if (task.actor_flies or task.actor_labels) and act_fn is None:
                raise ValueError('this landing needs the actor\'s weights')
            return fly_demo(self.env, task.seed, task.episode, np.random.default_rng(task.noise_seed), task.noise,
                            None if task.actor_labels else self.script,
                            label_fn=act_fn if task.actor_labels else None,
                            act_fn=act_fn if task.actor_flies else None, goal_labels=task.goal_labels)
        if task.kind == 'td3':
            return fly_td3(self.env, task, act_fn)
        if task.kind == 'eval':
            return run_episode(self.env, act_fn, task.seed, {'beta': task.beta})
        raise ValueError(f'unknown landing kind {task.kind!r}')

    def close(self) -> None:
        """Close the environment."""
        self.env.close()


class LandingPool(WorkerPool):
    """LandingWorkers on `workers` local processes or Ray actors (cluster.WorkerPool): `submit(task, weights)`,
    `map(tasks, weights)` in the tasks' order. An unknown demonstrator is refused here, not per task."""

    def __init__(self, env_cfg: EnvConfig, demo_policy: str, workers: int, ray_address: str = '') -> None:
        demonstrator(demo_policy, env_cfg.max_speed)
        super().__init__(functools.partial(LandingWorker, env_cfg, demo_policy), workers, ray_address,
                         'training landings')

    def map(self, tasks: Iterable[LandingTask], weights: ActorWeights | None = None) -> Iterator:
        """Fly every task (all submitted at once) with `weights` (sent to Ray once); results in the tasks' order."""
        if self.ray is not None and weights is not None:
            weights = self.ray.put(weights)
        return super().map(tasks, weights)


def collect_demos(env: LandingAssistEnv, episodes: int, noise: float, seed: int, buffer: ReplayBuffer,
                  demo_policy: str = 'oracle', act_fn=None, label_fn=None, desc: str = 'demonstrations',
                  pool: LandingPool | None = None, weights: ActorWeights | None = None, goal_labels: bool = False,
                  ) -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """Fly `episodes` landings into `buffer`; (obs, demonstrator actions, results).

    The demonstrator labels every state: the scripted assistant `demo_policy`, or for 'init_actor'
    `label_fn(obs)` (the starting actor, frozen: TD3+BC then anchors fine-tuning to it). It also flies
    (+ Gaussian `noise`) unless `act_fn(obs)` is given: then that policy flies and the demonstrator
    only labels (DAgger). With `goal_labels` each label is followed by the true goal (6 columns). With `pool`
    the landings are flown by its workers, `weights` being the actor
    that `act_fn`/`label_fn` compute (only whether each is given counts then). A progress bar (`desc`,
    landings) on stderr when it is a terminal.
    """
    script = demonstrator(demo_policy, env.cfg.max_speed)
    if script is None and label_fn is None:
        raise ValueError('demo_policy init_actor needs the starting actor (label_fn)')
    bar = tqdm(total=episodes, desc=desc, unit='landing', file=sys.stderr, mininterval=2, disable=None)
    if pool is None:
        rng = np.random.default_rng(seed)
        landings = (fly_demo(env, int(seed * 7919 + ep), ep, rng, noise, script, label_fn, act_fn, goal_labels)
                    for ep in range(episodes))
    else:
        if weights is None and (act_fn is not None or label_fn is not None):
            raise ValueError('a pool flies the actor from its weights: pass weights')
        landings = pool.map((LandingTask('demo', ep, int(seed * 7919 + ep), noise_seed=(seed, ep), noise=noise,
                                         actor_flies=act_fn is not None, actor_labels=script is None,
                                         goal_labels=goal_labels)
                             for ep in range(episodes)), weights)
    obs_l, act_l, results = [], [], []
    with bar:
        for landing in landings:
            landing.into(buffer)
            obs_l.append(landing.obs)
            act_l.append(landing.labels)
            results.append(landing.result)
            bar.update(1)
    if not obs_l:
        return (np.zeros((0, env.observation_space.shape[0]), np.float32),
                np.zeros((0, 6 if goal_labels else 3), np.float32), results)
    return np.concatenate(obs_l), np.concatenate(act_l), results
