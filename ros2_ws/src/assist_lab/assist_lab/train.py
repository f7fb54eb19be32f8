"""train_td3: train the assistant with TD3 against simulated pilots (resumable, background-friendly).

    train_td3 --name oracle_a --condition oracle --total-steps 2000000
    train_td3 --resume runs/oracle_a            # continue where it stopped, with the run's own settings

Every value is checked before any work (TrainArgs' field rules and check_relations, the files it
names, a run name that is a plain name and a run directory that holds no run yet): a bad one is one
`error:` line and exit status 2. A resumed run keeps the settings in its config.json: only
--total-steps, --torch-threads, --device, --workers and --ray may be given with other values; any other
flag that differs is an error naming each. `--workers N` flies the landings of every phase on N env
worker processes (`--ray ADDRESS`: Ray actors) while this process learns (assist_lab.collect).
A damaged checkpoint, or an actor that does not fit the run, is one `error:` line and exit status 1.
Run directory runs/<name>/: config.json, metrics.csv (one row per training landing), eval.csv
(periodic deterministic evaluation), progress.txt (last status line), checkpoint/ (state.pt +
replay.npz: the full training state, written as one unit: a crash leaves the previous checkpoint or
the new one, never a mix), actor_last.pt / actor_best.pt: shippable actors (``td3.load_actor``).
On --resume, metrics.csv and eval.csv rows written after the checkpoint are dropped (they are
flown again). Every file is written via a temporary file renamed into place (``assist_common.atomic``).
One run at a time per run directory: a second train_td3 on it (a new run of the same name, or a
--resume) exits with status 2 naming the process that holds it (<run>/.train_td3.lock, removed at the
end); so does a --ray address where no Ray cluster answers. A worker process that dies (killed, out of
memory) stops the run with one line and status 1 that says how to resume it; workers end with the
train_td3 process, even a SIGKILLed one.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import math
import sys
import time
import zipfile
from collections import deque
from collections.abc import Collection
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from assist_common.atomic import (CsvLog, atomic_dir, atomic_path, committed_dir, remove_stale_temporaries,
                                  truncate_csv, write_text_atomic)
from .curves import plot_curves
from assist_perception.model import load_training_state, training_device
from assist_sim.pilots import HELDOUT_FAMILIES, TRAIN_FAMILIES

from assist_common.settings import SettingsError, check_settings, exit_error, flag, parse_command, setting
from .cluster import DirectoryBusy, RayUnreachable, WorkerDied, exit_worker_died, hold_directory
from .collect import (DEMO_POLICIES, ActorWeights, LandingPool, LandingTask, collect_demos,
                      make_env)
from .episodes_plan import landing_seeds
from .env import PRIVILEGED_DIM, EnvConfig, LandingAssistEnv, RewardConfig, run_episode
from assist_policy.actor import MAX_HISTORY_S
from assist_policy.observation import (DISPLACEMENT_DIM, MAX_FEATURE_LAG_S, MAX_FEATURE_LAGS, feature_dim,
                                       history_steps)
from assist_policy.rules import rule, switched
from assist_policy.scripted import NEAREST_PAD_VARIANTS
from .td3 import TD3, OUNoise, ReplayBuffer, TD3Config, load_actor, save_actor

log = logging.getLogger(__name__)

EVAL_BETAS = (0.0, 0.25, 0.5, 0.75, 1.0)
CONDITIONS = ('oracle', 'latent', 'end_to_end')
MAX_SEED = 2**31 - 1


@dataclass
class TrainArgs:
    """Command-line arguments of train_td3 (every field is a --flag; values checked before any work)."""

    name: str = setting('td3_oracle', file_name=True)
    runs_dir: str = setting('runs', nonempty=True)
    resume: str = ''
    condition: str = setting('oracle', choices=CONDITIONS)
    seed: int = setting(0, ge=0, le=MAX_SEED)
    total_steps: int = setting(1_000_000, ge=0, le=10**10)
    start_steps: int = setting(5_000, ge=0)
    updates_per_step: float = setting(1.0, ge=0.0, le=100.0)
    buffer_size: int = setting(1_000_000, ge=1, le=10**8)
    preload: tuple[str, ...] = setting((), nonempty=True)
    ou_sigma: float = setting(0.3, ge=0.0, le=10.0)
    ou_sigma_min: float = setting(0.05, ge=0.0, le=10.0)
    ou_decay: float = setting(0.997, gt=0.0, le=1.0)
    ou_theta: float = setting(0.15, ge=0.0, le=1.0)
    eval_every_episodes: int = setting(50, ge=1)
    eval_episodes_per_beta: int = setting(4, ge=1, le=10_000)
    checkpoint_every_steps: int = setting(25_000, ge=1)
    save_buffer: bool = True
    alpha: float = setting(0.5, ge=0.0, le=1.0)
    max_episode_s: float = setting(60.0, gt=0.0, le=3600.0)
    encoder_path: str = ''
    landing_weight: float = setting(10.0, ge=0.0, le=1e6)
    progress_weight: float = setting(1.0, ge=0.0, le=1e6)
    progress_radius_m: float = setting(3.0, gt=0.0, le=100.0)
    action_weight: float = setting(0.01, ge=0.0, le=1e6)
    success_bonus: float = setting(0.0, ge=0.0, le=1e6)
    crash_penalty: float = setting(0.0, ge=0.0, le=1e6)
    torch_threads: int = setting(1, ge=1, le=256)
    device: str = setting('auto', choices=('auto', 'cpu', 'cuda'))
    demo_episodes: int = setting(0, ge=0, le=10**7)
    demo_noise: float = setting(0.2, ge=0.0, le=10.0)
    bc_steps: int = setting(0, ge=0)
    critic_warmup_updates: int = setting(0, ge=0)
    actor_start_steps: int = setting(0, ge=0)
    bc_alpha: float = setting(0.0, ge=0.0, le=1e6)
    demo_policy: str = setting('oracle', choices=DEMO_POLICIES)
    demo_bc_file: str = ''
    init_actor: str = ''
    dagger_rounds: int = setting(0, ge=0, le=10_000)
    dagger_episodes: int = setting(100, ge=1, le=10**7)
    hidden: tuple[int, ...] = setting((256, 256), ge=1, le=8192, min_len=1, max_len=16)   # as load_actor accepts
    actor_lr: float = setting(1e-3, gt=0.0, le=1.0)
    pilot: str = 'paper'
    paper_share: float = setting(0.0, ge=0.0, le=1.0)
    safety: bool = False
    override: bool = False
    floor_descent_weight: float = setting(0.0, ge=0.0, le=1e6)
    feature_lags_s: tuple[float, ...] = setting((), gt=0.0, le=MAX_FEATURE_LAG_S, max_len=MAX_FEATURE_LAGS)
    memory_displacement: bool = False
    history_s: float = setting(0.0, ge=0.0, le=MAX_HISTORY_S)
    history_step_s: float = setting(0.25, gt=0.0, le=MAX_HISTORY_S)
    history_hidden: int = setting(64, ge=1, le=4096)
    goal_head: bool = False
    goal_weight: float = setting(0.1, ge=0.0, le=1e6)
    asymmetric_critic: bool = False
    action_rate_weight: float = setting(0.0, ge=0.0, le=1e6)
    arducopter_share: float = setting(0.0, ge=0.0, le=1.0)
    arducopter_spread: float = setting(0.0, ge=0.0, lt=1.0)
    workers: int = setting(1, ge=0, le=1024)
    ray: str = ''

    def check_relations(self) -> None:
        """SettingsError when flags contradict each other (what training would refuse later, said up front)."""
        try:
            check_training_pilot(self.pilot)
        except ValueError as exc:
            raise SettingsError(f'--pilot: {exc}') from None
        if self.memory_displacement and not self.feature_lags_s:
            raise SettingsError('--memory-displacement true needs --feature-lags-s')
        if self.feature_lags_s and self.condition == 'end_to_end':
            raise SettingsError('--feature-lags-s needs the latent or oracle condition')
        if self.history_s > 0 and self.condition == 'end_to_end':
            raise SettingsError('--history-s needs the latent or oracle condition')
        try:
            history_steps(self.history_s, self.history_step_s)
        except ValueError as exc:
            raise SettingsError(f'--history-s/--history-step-s: {exc}') from None
        if self.goal_head and (self.demo_policy == 'init_actor' or self.demo_bc_file or not self.demo_episodes):
            raise SettingsError('--goal-head is cloned from the true goal of the scripted demonstrations this run '
                                'flies: it needs --demo-episodes with a scripted --demo-policy (no --demo-bc-file)')
        if self.goal_head and self.total_steps > 0 and not self.asymmetric_critic:
            raise SettingsError('--goal-head in a TD3 phase (--total-steps > 0) is kept trained on the true goal the '
                                'asymmetric critic\'s values carry: add --asymmetric-critic true')
        if self.condition != 'latent' and self.encoder_path:
            raise SettingsError('--encoder-path is only used by the latent condition')
        if self.resume:
            return                      # the run's saved settings decide the rest
        if self.dagger_rounds > 0 and not (self.demo_episodes > 0 or self.demo_bc_file):
            raise SettingsError('--dagger-rounds needs demonstrations (--demo-episodes or --demo-bc-file)')
        if self.demo_policy == 'init_actor' and not self.init_actor:
            raise SettingsError('--demo-policy init_actor needs --init-actor (the actor that labels the '
                                'demonstrations)')
        if self.demo_policy == 'init_actor' and self.dagger_rounds > 0:
            raise SettingsError('--demo-policy init_actor labels with the starting actor: DAgger would clone it '
                                'onto itself')


HELP = {
    'name': 'run name: the run directory is <runs-dir>/<name>',
    'resume': 'run directory to continue with the settings it was started with (its config.json); only '
              '--total-steps, --torch-threads, --device, --workers and --ray may be given with other values, any '
              'other flag that differs from the run\'s is an error naming it',
    'condition': 'oracle | latent | end_to_end',
    'total_steps': 'environment steps to train for (in total, across resumes)',
    'start_steps': 'initial steps with uniformly random actions',
    'updates_per_step': 'gradient updates per environment step',
    'preload': 'replay.npz files of earlier runs (runs/<name>/checkpoint/replay.npz, demos.npz) to preload into '
               'the buffer',
    'ou_sigma': 'initial Ornstein-Uhlenbeck noise scale (raw action units)',
    'ou_decay': 'noise scale multiplier per landing',
    'eval_every_episodes': 'deterministic evaluation every this many landings',
    'checkpoint_every_steps': 'write checkpoint/ (state.pt + replay.npz, one unit) every this many steps',
    'encoder_path': 'CM-VAE weights for the latent condition (default: the shipped model)',
    'torch_threads': 'torch CPU threads (the machine is shared)',
    'device': 'where the networks train: cuda (a GPU), cpu, or auto (cuda when torch sees one); a resumed run may '
              'change it',
    'demo_episodes': 'landings flown by the scripted oracle assistant to preload the buffer (paper: preload '
                     'from earlier models); saved to demos.npz',
    'demo_noise': 'Gaussian noise (raw action units) on the demonstrations, for action diversity',
    'bc_steps': 'supervised actor pre-training steps on the (noise-free) demonstration actions',
    'critic_warmup_updates': 'critic-only updates on the preloaded buffer before training starts',
    'actor_start_steps': 'update only the critic (on the run\'s own landings) until this many environment steps, '
                         'so a fine-tuned actor is not moved by a critic that has not yet seen it fly',
    'demo_policy': 'demonstrator: oracle (knows the goal), init_actor (the --init-actor itself, frozen: TD3+BC '
                   'fine-tuning anchored to the actor it starts from) or a nearest-pad teacher '
                   '(scripted.NEAREST_PAD_VARIANTS, each documented in ScriptedConfig; goal-agnostic and imitable '
                   'from the latent, but for nearest_pad_goal_commit, which helps over the goal pad only: a '
                   'privileged teacher for an actor that infers the goal): ' + ', '.join(NEAREST_PAD_VARIANTS),
    'demo_bc_file': 'demos_bc.npz of an earlier run: reuse its demonstrations for behaviour cloning / TD3+BC '
                    'instead of collecting new ones (preload its demos.npz with --preload)',
    'bc_alpha': 'TD3+BC regulariser weight (0 = plain TD3); keeps the actor near the demonstrations',
    'init_actor': 'actor file (e.g. a shipped models/td3_*_actor.pt) to start from instead of behaviour '
                  'cloning (--bc-steps then only applies to DAgger rounds)',
    'dagger_rounds': 'DAgger rounds before TD3: fly the current actor, label every visited state with the '
                     'scripted demonstrator, clone again (--bc-steps) on all demonstrations so far',
    'dagger_episodes': 'landings flown per DAgger round',
    'actor_lr': 'actor learning rate (paper: 1e-3; lower for fine-tuning a trained actor)',
    'pilot': 'simulated pilots to train with (domain randomisation): paper, a training family of '
             'assist_sim.pilots (TRAIN_FAMILIES) or train_mix (one training family per landing); the held-out '
             'families and mix are refused',
    'paper_share': 'chance per training landing of the paper pilot instead of --pilot (keeps the reference '
                   'pilot at a solid share of a population run)',
    'floor_descent_weight': 'safety reward term: cost per m/s of flown descent below 1.5 m with no pad under '
                            'the vehicle (0 = the paper reward)',
    'feature_lags_s': 'feature memory: the actor also sees the scene feature as it was this many seconds ago '
                      '(one copy per lag, e.g. 1 2); an --init-actor with fewer lags is widened with zero weights',
    'memory_displacement': 'with --feature-lags-s: the actor also sees how far the vehicle moved since each lagged '
                           'feature (odometry, 3 per lag); an --init-actor without them is widened with zero weights',
    'history_s': 'history window: the actor also sees the flight\'s last this many seconds (observation.HistoryWindow) '
                 'through a GRU (0 = none)',
    'history_step_s': 'seconds between the history window\'s rows',
    'history_hidden': 'GRU units reading the history window',
    'goal_head': 'the actor also estimates the goal (a Gaussian over its offset), cloned from the true goal in the '
                 'demonstrations and DAgger rounds',
    'goal_weight': 'weight of the goal head\'s negative log-likelihood in cloning',
    'asymmetric_critic': 'the TD3 critic also sees what only the simulator knows (the true goal, the pilot\'s own '
                         'goal estimate, alpha and beta: env.privileged), the actor never; the buffer then keeps '
                         'those values beside each observation (its files and --preload files hold them too)',
    'action_rate_weight': 'reward term: cost per m/s of change in the assistant action between steps (0 = the '
                          'paper reward)',
    'workers': 'env workers flying the landings of every phase (demonstrations, DAgger, TD3 collection, evaluation) '
               'while this process learns: 1 = all in this process (the single-process run, unchanged); 0 = one '
               'per CPU core (or per CPU of the --ray cluster). More than one changes the TD3 run: see '
               'assist_lab.collect',
    'ray': 'run the env workers as actors on a Ray cluster at this address (ray://HOST:10001 or HOST:6379; auto: '
           'a local instance) instead of local processes; needs the optional ray package',
    'arducopter_share': 'share of the landings (drawn per landing) flown on the ArduCopter GUIDED plant '
                        '(assist_sim.core.arducopter) instead of the ideal velocity loop',
    'arducopter_spread': 'on those landings, scale each of the ArduCopter model\'s dynamic settings by a uniform '
                         'factor in [1 - spread, 1 + spread] (0.3: +-30 %%)',
    'safety': 'fly with the floor guard (assist_policy.safety) on, as policy_node does by default',
    'override': 'fly with the pilot override (assist_policy.override) on, as policy_node does by default; '
                'TD3 transitions store the actor\'s action, so while the override acts the critic sees it as '
                'part of the environment (as it sees the floor guard)',
}



def check_training_pilot(name: str) -> None:
    """ValueError unless `name` is a pilot training may use (never a held-out family or the held-out mix)."""
    if name not in TRAIN_FAMILIES + ('train_mix',):
        raise ValueError(f'pilot {name!r} is not for training: use one of {", ".join(TRAIN_FAMILIES)} or '
                         f'train_mix (held out for evaluation only: {", ".join(HELDOUT_FAMILIES)}, mix, '
                         'approach_mix)')


def env_config_from(args: TrainArgs) -> EnvConfig:
    """The task the run trains on."""
    check_training_pilot(args.pilot)
    return EnvConfig(condition=args.condition, alpha=args.alpha, max_episode_s=args.max_episode_s,
                     encoder_path=args.encoder_path, pilot_family=args.pilot, paper_share=args.paper_share,
                     feature_lags_s=tuple(args.feature_lags_s), memory_displacement=bool(args.memory_displacement),
                     history_s=float(args.history_s), history_step_s=float(args.history_step_s),
                     arducopter_share=float(args.arducopter_share), arducopter_spread=float(args.arducopter_spread),
                     safety=switched(rule('safety'), args.safety), override=switched(rule('override'), args.override),
                     reward=RewardConfig(landing_weight=args.landing_weight,
                                         progress_weight=args.progress_weight,
                                         progress_radius_m=args.progress_radius_m,
                                         action_weight=args.action_weight,
                                         success_bonus=args.success_bonus,
                                         crash_penalty=args.crash_penalty,
                                         floor_descent_weight=args.floor_descent_weight,
                                         action_rate_weight=args.action_rate_weight))


def evaluate_agent(env: LandingAssistEnv | None, agent: TD3, per_beta: int, seed: int = 12345,
                   pool: LandingPool | None = None) -> dict:
    """Deterministic evaluation on fixed seeds over EVAL_BETAS; mean error, success, crash rates (flown in
    `env`, or by `pool`'s workers when given: the same landings; `env` is then not used)."""
    plan = landing_seeds(seed, EVAL_BETAS, per_beta)
    if pool is None:
        rows = [run_episode(env, agent.act, s, {'beta': beta}) for s, beta in plan]
    else:
        rows = list(pool.map((LandingTask('eval', i, s, beta=beta) for i, (s, beta) in enumerate(plan)),
                             ActorWeights.of(agent.actor, agent.meta)))
    err = np.array([r['error_m'] for r in rows])
    return {'eval_error_mean': float(err.mean()), 'eval_error_std': float(err.std()),
            'eval_success': float(np.mean([r['success'] for r in rows])),
            'eval_crash': float(np.mean([r['crash'] for r in rows])),
            'eval_active': float(np.mean([r['active_fraction'] for r in rows]))}


def widen_state(state: dict, src_lags: list, dst_lags: list, dst_vec_dim: int, feat_dim: int,
                src_displacement: bool = False, dst_displacement: bool = False) -> dict:
    """An actor state dict for more feature lags and/or memory displacement: new inputs get zero weights.

    Layout (observation.py): [base vector | feature per lag | displacement per lag (if any)]. The
    widened actor acts exactly like the original until training moves the new weights. ValueError
    unless the source's lags are a prefix of the destination's, a source with displacement keeps it
    with the same lags, and the sizes fit.
    """
    if list(dst_lags[:len(src_lags)]) != list(src_lags):
        raise ValueError(f'feature lags {list(src_lags)} are not a prefix of {list(dst_lags)}')
    if src_displacement and not (dst_displacement and list(src_lags) == list(dst_lags)):
        raise ValueError('an actor with memory displacement can only be widened to the same lags with displacement')
    state = dict(state)
    w = state['head.0.weight']
    n_src, n_dst = len(src_lags), len(dst_lags)
    src_disp = DISPLACEMENT_DIM * n_src if src_displacement else 0
    dst_disp = DISPLACEMENT_DIM * n_dst if dst_displacement else 0
    kept = w.shape[1] - src_disp                   # base vector + the source's lagged features
    if kept + (n_dst - n_src) * feat_dim + dst_disp != dst_vec_dim:
        raise ValueError(f'actor has {w.shape[1]} inputs, which do not widen to the {dst_vec_dim} of this run')
    new = torch.zeros(w.shape[0], dst_vec_dim, dtype=w.dtype)
    new[:, :kept] = w[:, :kept]
    if src_disp:
        new[:, dst_vec_dim - dst_disp:] = w[:, kept:]
    state['head.0.weight'] = new
    return state


def init_actor(agent: TD3, path: str, condition: str) -> None:
    """Start from a saved actor (actor and its target); ValueError if it does not fit this run."""
    actor, meta = load_actor(path)
    if meta.get('condition', condition) != condition:
        raise ValueError(f'{path}: actor was trained for {meta.get("condition")!r}, this run is {condition!r}')
    state = actor.state_dict()
    dst_lags = agent.meta.get('feature_lags_s', [])
    dst_disp = bool(agent.meta.get('memory_displacement', False))
    for key in ('history_s', 'history_step_s', 'history_hidden', 'goal_head'):
        if key in agent.meta and meta[key] != agent.meta[key]:
            raise ValueError(f'{path}: actor has {key} {meta[key]!r}, this run {agent.meta[key]!r}')
    if list(meta['feature_lags_s']) != list(dst_lags) or meta['memory_displacement'] != dst_disp:
        state = widen_state(state, meta['feature_lags_s'], dst_lags, agent.meta['vec_dim'],
                            feature_dim(condition, int(agent.meta.get('latent_dim', 0))),
                            meta['memory_displacement'], dst_disp)
        log.info('actor widened from feature lags %s (displacement %s) to %s (displacement %s); new inputs start '
                 'at zero weight', meta['feature_lags_s'], meta['memory_displacement'], dst_lags, dst_disp)
    try:
        agent.actor.load_state_dict(state)
    except RuntimeError as exc:
        raise ValueError(f'{path}: actor does not fit this run (observation size / hidden layers): {exc}') from exc
    agent.actor_target.load_state_dict(state)
    log.info('actor initialised from %s', path)


CHECKPOINT_DIR = 'checkpoint'
# flags a resumed run takes from the command line
RESUME_MAY_CHANGE = ('resume', 'total_steps', 'torch_threads', 'device', 'workers', 'ray')


def _plain(value):
    """A settings value as config.json holds it (tuples as lists), for comparing."""
    return list(value) if isinstance(value, (tuple, list)) else value


def resumed_args(args: TrainArgs, given: Collection[str] | None = None) -> TrainArgs:
    """The settings `args.resume`'s run continues with: its config.json, plus --total-steps/--torch-threads.

    `given`: the flags of the command line (None: the fields that differ from TrainArgs' defaults).
    SettingsError (one line) when the directory holds no readable train_td3 config.json, its settings
    are no longer valid, or a given flag asks for another value than the run was started with (each
    is named: a resumed run keeps its settings).
    """
    run_dir = Path(args.resume)
    cfg_file = run_dir / 'config.json'
    if not run_dir.is_dir():
        raise SettingsError(f'--resume {run_dir}: no such run directory')
    try:
        saved = json.loads(cfg_file.read_text(encoding='utf-8'))['train']
        if not isinstance(saved, dict):
            raise TypeError('"train" is not a mapping')
    except FileNotFoundError:
        raise SettingsError(f'--resume {run_dir}: no config.json (not a train_td3 run directory)') from None
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SettingsError(f'--resume {run_dir}: damaged config.json ({type(exc).__name__}: '
                            f'{str(exc).splitlines()[0] if str(exc) else ""})') from None
    unknown = sorted(set(saved) - {f.name for f in dataclasses.fields(TrainArgs)})
    if unknown:
        raise SettingsError(f'--resume {run_dir}: config.json holds settings train_td3 does not know: '
                            f'{", ".join(map(str, unknown))}')
    resumed = TrainArgs(**{k: tuple(v) if isinstance(v, list) else v for k, v in saved.items()})
    resumed.resume = str(run_dir)
    try:
        check_settings(resumed)
    except SettingsError as exc:
        raise SettingsError(f'--resume {run_dir}: config.json: {exc}') from None
    if given is None:
        defaults = TrainArgs()
        given = [f.name for f in dataclasses.fields(TrainArgs) if getattr(args, f.name) != getattr(defaults, f.name)]
    changed = [f'{flag(n)} (run: {_plain(getattr(resumed, n))}, given: {_plain(getattr(args, n))})'
               for n in sorted(set(given) - set(RESUME_MAY_CHANGE))
               if _plain(getattr(args, n)) != _plain(getattr(resumed, n))]
    if changed:
        raise SettingsError(f'--resume {run_dir}: the run was started with other settings: {"; ".join(changed)}. '
                            'A resumed run keeps its settings (only --total-steps, --torch-threads, --device, '
                            '--workers and --ray may change): '
                            'drop these flags, or start a new run with another --name')
    for n in RESUME_MAY_CHANGE[1:]:
        if n in given:
            setattr(resumed, n, getattr(args, n))
    return resumed


def prepare_run(args: TrainArgs, given: Collection[str] | None = None) -> TrainArgs:
    """Checked settings of a run, before any work: resolved from config.json on --resume; SettingsError (one line).

    Besides each flag's rule: a new run needs a run directory that holds no run yet, and the files it
    names (--preload, --init-actor, --demo-bc-file, --encoder-path) must exist.
    """
    check_settings(args)
    if args.resume:
        args = resumed_args(args, given)
    else:
        run_dir = Path(args.runs_dir) / args.name
        check_new_run_dir(run_dir)
        if run_dir.exists() and not run_dir.is_dir():
            raise SettingsError(f'{run_dir} exists and is not a directory')
        for name, paths in (('preload', args.preload), ('init_actor', [args.init_actor] if args.init_actor else []),
                            ('demo_bc_file', [args.demo_bc_file] if args.demo_bc_file else [])):
            for path in paths:
                if not Path(path).is_file():
                    raise SettingsError(f'{flag(name)} {path}: no such file')
    if args.encoder_path and not Path(args.encoder_path).is_file():
        raise SettingsError(f'--encoder-path {args.encoder_path}: no such file')
    training_device(args.device)      # --device cuda without a GPU: refused before any work
    return args


def check_new_run_dir(run_dir: Path) -> None:
    """SettingsError (one line) when `run_dir` already holds a run (its config.json or a checkpoint)."""
    if (run_dir / 'config.json').exists() or committed_dir(run_dir / CHECKPOINT_DIR) is not None:
        raise SettingsError(f'{run_dir} already holds a run: continue it with --resume {run_dir} or choose '
                            'another --name')


def save_checkpoint(run_dir: Path, agent: TD3, buffer: ReplayBuffer | None, step: int, episode: int,
                    best: float) -> Path:
    """Write the training state (agent, counters, replay buffer) as one unit: run_dir/checkpoint/."""
    path = run_dir / CHECKPOINT_DIR
    with atomic_dir(path) as tmp:
        torch.save({'agent': agent.state_dict(), 'step': step, 'episode': episode, 'best': best,
                    'buffer_size': None if buffer is None else buffer.size}, tmp / 'state.pt')
        if buffer is not None:
            buffer.save(tmp / 'replay.npz')
    return path


STATE_KEYS = ('agent', 'step', 'episode', 'best')


def _load_state(path: Path) -> dict:
    """A checkpoint's state.pt (weights_only); ValueError (one line) when it is damaged."""
    return load_training_state(path, STATE_KEYS)


def load_checkpoint(run_dir: Path) -> tuple[dict, Path | None] | None:
    """(state, replay.npz or None) of the last complete checkpoint of a run, or None if it has none.

    ValueError (one line, naming the file) when the checkpoint is damaged.
    """
    path = committed_dir(run_dir / CHECKPOINT_DIR)
    if path is None:
        legacy = run_dir / 'ckpt.pt'       # runs from before checkpoints were written as one unit
        if not legacy.exists():
            return None
        log.warning('%s: old checkpoint layout (ckpt.pt + replay.npz written one by one): their steps may '
                    'disagree', run_dir)
        state = _load_state(legacy)
        replay = run_dir / 'replay.npz'
        return state, replay if replay.exists() else None
    state = _load_state(path / 'state.pt')
    replay = path / 'replay.npz'
    if state.get('buffer_size') is not None and not replay.exists():
        raise ValueError(f'{path}: checkpoint lacks replay.npz')
    return state, replay if replay.exists() else None


def _restore(agent: TD3, buffer: ReplayBuffer, state: dict, replay: Path | None, run_dir: Path) -> None:
    """Load a checkpoint's agent and replay buffer; ValueError (one line) when they are damaged or do not fit."""
    try:
        agent.load_state_dict(state['agent'])
    except (RuntimeError, ValueError, KeyError, TypeError, AttributeError) as exc:
        first = (str(exc).strip().splitlines() or [''])[0][:200]
        raise ValueError(f'damaged checkpoint in {run_dir}: agent state: {type(exc).__name__}: {first}') from None
    if replay is not None:
        try:
            buffer.load(replay)
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            first = (str(exc).strip().splitlines() or [''])[0][:200]
            raise ValueError(f'damaged checkpoint {replay}: {type(exc).__name__}: {first}') from None


def _best_on_disk(path: Path) -> float:
    """Eval error recorded in actor_best.pt (inf if absent or unreadable)."""
    try:
        return float(load_actor(path)[1]['eval']['eval_error_mean'])
    except (ValueError, KeyError, TypeError):
        return math.inf


def train(args: TrainArgs, given: Collection[str] | None = None) -> Path:
    """Train (or resume) a run; returns the run directory.

    `given`: the flags of the command line (see `resumed_args`). SettingsError before anything is
    written for bad settings (`prepare_run`), RayUnreachable for a --ray address where no Ray cluster
    answers, DirectoryBusy when another process runs in the run directory, ValueError for a damaged
    checkpoint, WorkerDied when a worker process dies. With `args.workers` other than 1 (or `args.ray`)
    the landings are flown by a LandingPool's workers (assist_lab.collect), closed when training ends.
    """
    args = prepare_run(args, given)
    pool = (LandingPool(env_config_from(args), args.demo_policy, args.workers, args.ray)
            if args.workers != 1 or args.ray else None)
    run_dir = Path(args.resume) if args.resume else Path(args.runs_dir) / args.name
    try:
        # one run per directory: two would write the same metrics, checkpoints and actors over each other
        with hold_directory(run_dir, 'train_td3', 'wait for it to end, or choose another --name'):
            if not args.resume:
                check_new_run_dir(run_dir)      # again, held: a run started since prepare_run looked
            try:
                return _train(args, pool)
            except WorkerDied as exc:
                raise WorkerDied(f'{exc}; continue the run from its last checkpoint with: train_td3 --resume '
                                 f'{run_dir}') from None
    finally:
        if pool is not None:
            pool.close()


def _train(args: TrainArgs, pool: LandingPool | None) -> Path:
    """train() with checked settings: in this process, or with `pool` flying the landings."""
    torch.set_num_threads(args.torch_threads)
    run_dir = Path(args.resume) if args.resume else Path(args.runs_dir) / args.name
    saved = load_checkpoint(run_dir) if args.resume else None      # a damaged state.pt stops us here
    run_dir.mkdir(parents=True, exist_ok=True)
    for stale in remove_stale_temporaries(run_dir):
        log.info('removed %s (left by an interrupted write)', stale)
    env_cfg = env_config_from(args)
    env = make_env(env_cfg)
    eval_env = make_env(env_config_from(args)) if pool is None else None    # a pool's workers evaluate
    td3_cfg = TD3Config(hidden=args.hidden, actor_lr=args.actor_lr, history_hidden=args.history_hidden,
                        goal_head=args.goal_head, goal_weight=args.goal_weight,
                        privileged_dim=PRIVILEGED_DIM if args.asymmetric_critic else 0)
    write_text_atomic(run_dir / 'config.json', json.dumps(
        {'train': dataclasses.asdict(args), 'env': dataclasses.asdict(env_cfg), 'td3': dataclasses.asdict(td3_cfg)},
        indent=2, default=str))
    obs_dim = env.observation_space.shape[0]
    device = training_device(args.device)
    log.info('training on %s', device)
    window = env.builder.window
    agent = TD3(obs_dim - env.image_size, cfg=td3_cfg, image=env.image_size > 0, seed=args.seed, device=device,
                history_steps=window.steps, history_row=window.row_dim if window.steps else 0)
    agent.meta.update(condition=args.condition, latent_dim=int(env_cfg.latent_dim),
                      max_speed=list(env_cfg.max_speed), blend_threshold=env_cfg.blend_threshold,
                      window_s=env_cfg.window_s, feature_lags_s=list(env_cfg.feature_lags_s),
                      memory_displacement=bool(env_cfg.memory_displacement), history_s=float(env_cfg.history_s),
                      history_step_s=float(env_cfg.history_step_s))
    obs_dtype = np.float16 if env.image_size else np.float32
    buffer = ReplayBuffer(obs_dim, 3, args.buffer_size, obs_dtype=obs_dtype, priv_dim=td3_cfg.privileged_dim)
    rng = np.random.default_rng(args.seed)
    noise = OUNoise(3, args.ou_theta, args.ou_sigma, args.ou_sigma_min, args.ou_decay, rng=rng)
    step, episode, best = 0, 0, math.inf
    if saved is not None:
        state, replay = saved
        _restore(agent, buffer, state, replay, run_dir)
        step, episode, best = int(state['step']), int(state['episode']), float(state['best'])
        noise.landings = episode
        if state.get('buffer_size') is not None and buffer.size != int(state['buffer_size']):
            raise ValueError(f'{run_dir}: checkpoint at step {step} holds {buffer.size} transitions, '
                             f'expected {state["buffer_size"]}')
        rng = np.random.default_rng([args.seed, episode])
        noise.rng = rng
        # rows logged after this checkpoint are flown again: drop them so none is counted twice
        for name in ('metrics.csv', 'eval.csv'):
            n = truncate_csv(run_dir / name, lambda row, e=episode: int(row['episode']) <= e)
            if n:
                log.info('%s: dropped %d rows logged after the checkpoint', name, n)
        best = min(best, _best_on_disk(run_dir / 'actor_best.pt'))
        log.info('resumed %s at step %d, episode %d, buffer %d', run_dir, step, episode, buffer.size)
    def snapshot() -> ActorWeights | None:
        """The actor as the pool's workers fly it now (None without a pool)."""
        return None if pool is None else ActorWeights.of(agent.actor, agent.meta)

    demos = None
    if args.bc_alpha > 0 and args.resume and (run_dir / 'demos_bc.npz').exists():
        with np.load(run_dir / 'demos_bc.npz', allow_pickle=False) as data:
            demos = (data['obs'], data['act'])
    for path in () if args.resume else args.preload:   # on resume replay.npz already holds them
        log.info('preloaded %d transitions from %s', buffer.load(path), path)
    has_demos = not args.resume and bool(args.demo_episodes > 0 or args.demo_bc_file)
    anchored = args.demo_policy == 'init_actor'     # TrainArgs.check_relations: it comes with --init-actor
    if has_demos and anchored and not args.resume:
        init_actor(agent, args.init_actor, args.condition)    # it labels the demonstrations
    if has_demos:
        if args.demo_bc_file:
            with np.load(args.demo_bc_file, allow_pickle=False) as data:
                d_obs, d_act = data['obs'], data['act']
            if d_obs.shape[1] != obs_dim:
                raise ValueError(f'{args.demo_bc_file}: observation size {d_obs.shape[1]} != {obs_dim}')
            log.info('demonstrations: %d transitions from %s', len(d_obs), args.demo_bc_file)
        else:
            d_obs, d_act, d_res = collect_demos(env, args.demo_episodes, args.demo_noise, args.seed + 17, buffer,
                                                  args.demo_policy, label_fn=agent.act if anchored else None,
                                                  pool=pool, weights=snapshot() if anchored else None,
                                                  goal_labels=args.goal_head)
            err = np.mean([r['error_m'] for r in d_res])
            succ = np.mean([r['success'] for r in d_res])
            log.info('demonstrations: %d landings, %d transitions, error %.3f m, success %.2f',
                     len(d_res), len(d_obs), err, succ)
            buffer.save(run_dir / 'demos.npz')
        if args.bc_steps > 0 and not args.init_actor:
            mse = agent.behaviour_clone(d_obs, d_act, args.bc_steps)
            log.info('behaviour cloning: %d steps, final MSE %.4f', args.bc_steps, mse)
    if not args.resume and args.init_actor:
        init_actor(agent, args.init_actor, args.condition)
    if has_demos:
        for rnd in range(args.dagger_rounds):
            o, a, res = collect_demos(env, args.dagger_episodes, 0.0, args.seed * 1009 + 31 * (rnd + 1), buffer,
                                      args.demo_policy, act_fn=agent.act,
                                      desc=f'DAgger {rnd + 1}/{args.dagger_rounds}', pool=pool, weights=snapshot(),
                                      goal_labels=args.goal_head)
            d_obs, d_act = np.concatenate([d_obs, o]), np.concatenate([d_act, a])
            mse = agent.behaviour_clone(d_obs, d_act, args.bc_steps)
            log.info('DAgger round %d: actor flew %d landings (error %.3f m, success %.2f, crash %.2f); '
                     '%d labelled states in all, cloning MSE %.4f', rnd + 1, len(res),
                     np.mean([r['error_m'] for r in res]), np.mean([r['success'] for r in res]),
                     np.mean([r['crash'] for r in res]), len(d_obs), mse)
        with atomic_path(run_dir / 'demos_bc.npz') as tmp:          # what --resume's TD3+BC term reads
            np.savez(tmp, obs=d_obs, act=d_act)
        demos = (d_obs, d_act) if args.bc_alpha > 0 else None
        for _ in tqdm(range(args.critic_warmup_updates), desc='critic warm-up', unit='update', file=sys.stderr,
                      mininterval=2, disable=None):
            agent.update(buffer, train_actor=False)
        if args.critic_warmup_updates:
            log.info('critic warm-up: %d updates', args.critic_warmup_updates)
    metrics = CsvLog(run_dir / 'metrics.csv', ['episode', 'step', 'beta', 'return', 'error_m', 'outcome',
                                               'success', 'crash', 'active_fraction', 'sigma',
                                               'critic_loss', 'q_mean', 'wall_s'])
    evals = CsvLog(run_dir / 'eval.csv', ['episode', 'step', 'eval_error_mean', 'eval_error_std',
                                          'eval_success', 'eval_crash', 'eval_active', 'wall_s'])
    t0 = time.time()
    bar = tqdm(total=args.total_steps, initial=min(step, args.total_steps), desc=args.name, mininterval=2,
               file=sys.stderr, unit='step', dynamic_ncols=False)
    update_credit = 0.0

    def draw_curves() -> None:
        plot_curves(run_dir / 'eval.csv', run_dir / 'learning_curve.png', 'step',
                    [['eval_error_mean'], ['eval_success', 'eval_crash']], title=f'train_td3 {args.name}: evaluations')
        plot_curves(run_dir / 'metrics.csv', run_dir / 'training_landings.png', 'episode', [['error_m'], ['return']],
                    title=f'train_td3 {args.name}: training landings', smooth=50)

    def checkpoint() -> None:
        metrics.sync()
        evals.sync()
        draw_curves()
        save_checkpoint(run_dir, agent, buffer if args.save_buffer else None, step, episode, best)
        save_actor(agent.actor, agent.meta, run_dir / 'actor_last.pt')

    def run_eval() -> None:
        nonlocal best
        ev = evaluate_agent(eval_env, agent, args.eval_episodes_per_beta, pool=pool)
        ev.update(episode=episode, step=step, wall_s=round(time.time() - t0, 1))
        evals.write(ev)
        if ev['eval_error_mean'] < best:
            best = ev['eval_error_mean']
            save_actor(agent.actor, {**agent.meta, 'eval': ev}, run_dir / 'actor_best.pt')
        msg = (f'step {step} ep {episode} eval err {ev["eval_error_mean"]:.3f} '
               f'succ {ev["eval_success"]:.2f} crash {ev["eval_crash"]:.2f} best {best:.3f}')
        write_text_atomic(run_dir / 'progress.txt', msg + '\n')
        evals.sync()
        draw_curves()
        log.info(msg)

    def stepped(losses: list[dict]) -> None:
        """Count one environment step: progress, the updates it earns, a checkpoint when one is due."""
        nonlocal step, update_credit
        step += 1
        if step <= args.total_steps:        # the landing under way finishes past the budget
            bar.update(1)
        if buffer.size >= agent.cfg.batch_size and step >= min(args.start_steps, 1000):
            update_credit += args.updates_per_step
            while update_credit >= 1.0:
                losses.append(agent.update(buffer, train_actor=step >= args.actor_start_steps, demos=demos,
                                           bc_alpha=args.bc_alpha))
                update_credit -= 1.0
        if step % args.checkpoint_every_steps == 0:
            checkpoint()

    def landed(res: dict, beta: float, episode_return: float, active_fraction: float, sigma: float,
               losses: list[dict]) -> None:
        """Count one training landing: its metrics row, an evaluation when one is due."""
        nonlocal episode
        episode += 1
        cl = [loss['critic_loss'] for loss in losses]
        qm = [loss['q_mean'] for loss in losses]
        metrics.write({'episode': episode, 'step': step, 'beta': round(beta, 3),
                       'return': round(episode_return, 3), 'error_m': round(res['error_m'], 3),
                       'outcome': res['outcome'], 'success': int(res['success']),
                       'crash': int(res['crash']), 'active_fraction': round(active_fraction, 3),
                       'sigma': round(sigma, 4),
                       'critic_loss': round(float(np.mean(cl)), 4) if cl else '',
                       'q_mean': round(float(np.mean(qm)), 3) if qm else '',
                       'wall_s': round(time.time() - t0, 1)})
        if episode % args.eval_every_episodes == 0 and step >= args.start_steps:
            run_eval()

    def fly_here() -> None:
        """TD3 collection in this process: one landing after another, updates interleaved with its steps."""
        while step < args.total_steps:
            obs, info = env.reset(seed=int(args.seed * 1_000_003 + episode))
            priv = env.privileged() if buffer.priv_dim else None
            noise.reset()
            losses: list[dict] = []
            n_active = n_steps = 0
            while True:
                if step < args.start_steps:
                    act = rng.uniform(-1.0, 1.0, 3)
                else:
                    act = np.clip(agent.act(obs) + noise.sample(), -1.0, 1.0)
                nxt, rew, term, trunc, sinfo = env.step(act)
                nxt_priv = env.privileged() if buffer.priv_dim else None
                buffer.add(obs, act, rew, nxt, term or trunc, priv, nxt_priv)
                obs, priv = nxt, nxt_priv
                n_steps += 1
                n_active += int(sinfo['active'])
                stepped(losses)
                if term or trunc:
                    break
            noise.landed()
            landed(sinfo['result'], info['beta'], env.episode_return, n_active / n_steps, noise.sigma, losses)

    def fly_on_pool() -> None:
        """TD3 collection by the pool's workers: `workers` landings in flight, taken in episode order
        (assist_lab.collect says what differs from fly_here)."""
        pending: deque = deque()
        dispatched = episode

        def dispatch() -> None:
            nonlocal dispatched
            task = LandingTask('td3', dispatched, int(args.seed * 1_000_003 + dispatched),
                               noise_seed=(args.seed, dispatched), random_actions=step < args.start_steps,
                               ou=(args.ou_theta, args.ou_sigma, args.ou_sigma_min, args.ou_decay, dispatched))
            pending.append(pool.submit(task, None if task.random_actions else snapshot()))
            dispatched += 1
        try:
            while step < args.total_steps:
                while len(pending) < pool.workers:
                    dispatch()
                landing = pool.result(pending.popleft())
                landing.into(buffer)
                losses: list[dict] = []
                for _ in range(landing.steps):
                    stepped(losses)
                noise.landings = landing.episode + 1        # the scale as fly_here logs it: after the landing
                landed(landing.result, landing.beta, landing.episode_return, landing.active_steps / landing.steps,
                       noise.sigma, losses)
        finally:
            for handle in pending:      # past the budget, or stopped: landings in flight are not used
                pool.cancel(handle)

    try:
        if not args.resume and (args.bc_steps > 0 or args.critic_warmup_updates > 0 or args.init_actor
                                or args.dagger_rounds):
            run_eval()
        if pool is None:
            fly_here()
        else:
            fly_on_pool()
        if not math.isfinite(best):     # no evaluation ran: evaluate the final actor (progress.txt, actor_best.pt)
            run_eval()
        checkpoint()
    finally:
        bar.close()
        metrics.close()
        evals.close()
        env.close()
        if eval_env is not None:
            eval_env.close()
    return run_dir


def main(argv: list[str] | None = None) -> int:
    """Console entry point."""
    cmd = parse_command(TrainArgs, 'train_td3', __doc__, HELP, argv)
    parser, args, given = cmd.parser, cmd.settings, cmd.given
    try:
        args = prepare_run(args, given)
    except SettingsError as exc:
        parser.error(str(exc))
    try:
        with logging_redirect_tqdm():       # log lines above the progress bars, not through them
            run_dir = train(args)
    except (DirectoryBusy, RayUnreachable, SettingsError) as exc:    # the run directory or --ray cannot be used
        exit_error(parser.prog, exc, 2)
    except WorkerDied as exc:
        exit_worker_died(f'{parser.prog}: error: {exc}')
    except (ValueError, OSError) as exc:     # damaged checkpoint, an actor that does not fit, disk full
        log.debug('train_td3 failed', exc_info=True)
        exit_error(parser.prog, exc, 1)
    print(f'run directory: {run_dir}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
