"""evaluate: the paper's simulated-user experiment (Fig. 5 / Table I) in the LandingWorld.

Simulated pilots at alpha = 0.5 and beta = 0, 0.05, ..., 1 land `--landings` times per beta (40 in the
paper) unassisted and with each assistant (latent, oracle, end_to_end). Landing k at beta index b uses
the same scene, goal and pilot randomness in every condition (paired comparison; seeded).

    evaluate --out runs/eval_full                       # full experiment, shipped models, as policy_node flies them
    evaluate --out runs/eval_bare --safety false --override false --recall false --damper false   # bare actors
    evaluate --landings 4 --betas 0 0.5 1 --conditions unassisted oracle   # quick look
    evaluate --from-csv runs/eval_a/landings.csv runs/eval_b/landings.csv --out runs/eval_ab   # combine

Writes <out>/landings.csv (one row per landing), <out>/summary.csv, <out>/error_vs_beta.png and
prints the table: mean +- std error, median, specified-platform success (all legs on the goal),
nearest-platform success (all legs on the platform nearest to where it stopped, whichever it is),
crash rate and how often the landed platform was the goal. `misaimed` is the share of landings whose
pilot set off for another pad (its first goal estimate was nearest a pad other than the goal; the
column aimed_index), and `misaimed_success` how many of those still ended on the goal: a
goal-agnostic assistant can only get these right by reading the pilot's corrections.

Pilots other than the paper's: `--pilot <family|mix|train_mix>` flies every landing with a
pilot of that assist_sim.pilots family (`mix`: a held-out family drawn per landing); the column `pilot`
names the family flown.

The non-learned rules policy_node runs are on by default here too, as policy_node's defaults for each
mode, so `evaluate` measures the assistant as
it is deployed: the floor guard for every assisted condition, the pilot override, pad recall and
oscillation damper for latent and end_to_end but not for the oracle (it knows the goal: yielding to the
pilot or steering to the nearest pad only costs it). `--override/--recall/--damper true|false` set them
for every learned assistant; `--safety false --override false --recall false --damper false` flies the
bare learned actor, as the paper did. `--safety`: the floor guard (assist_policy.safety) for every
assisted condition, rows named `<condition>+guard` (so runs with and without it combine with --from-csv);
`guard_fraction` is the share of steps it acted, `wall_fraction` the share its wall rule
(assist_policy.walls) stopped an approach to a wall. `--override`: the pilot override
(assist_policy.override) for the learned assistants (not for the scripted references, which stay as
defined): rows `<condition>[+guard]+override`, `override_fraction` the share of steps it replaced the
actor's action. `--recall`: the pad recall (assist_policy.recall) for the learned assistants: rows
`<condition>[+guard][+override]+recall`, `recall_fraction` the share of steps it steered. `--damper`: the
oscillation damper (assist_policy.damper) for the learned assistants: rows
`<condition>[+guard][+override][+recall]+damper`, `damper_fraction` the share of steps it damped.

    evaluate --pilot bang_bang --betas 0 0.25 0.5 0.75 1 --landings 8 --out runs/eval_bang_bang

The assistant's intent as the pilot station shows it (assist_policy.intent: the pad its command steers to, the
descend/hold light): `--cues` shows it to the pilots of the assisted conditions (rows `<condition>...+cues`), who
read it in a share `--cue-trust` of their landings (assist_sim.cues). Every row records `duration_s` (time to
land) and `path_m` (the distance flown): `compare_landings` of a run with and without `--cues` on the same
landings pairs them, and the wrong-pad landings.

    evaluate --conditions latent --pilot mix --betas 0 0.25 0.5 0.75 1 --landings 24 --out runs/plain
    evaluate --conditions latent --pilot mix --betas 0 0.25 0.5 0.75 1 --landings 24 --cues --out runs/cues
    compare_landings --a runs/plain --b runs/cues

Landings are independent tasks keyed by (condition, beta, seed), flown from their own seeds: `--workers N`
flies them on N processes, `--ray ADDRESS` (or auto) as tasks on a Ray cluster, with the rows of a
one-process run either way, and a progress bar shows the run.

Results are crash-safe: landings go to <out>/landings.partial.csv as they are flown (the run's settings beside
it in landings.partial.json); an earlier landings.csv stays untouched until the run ends, when the complete
table replaces it in one rename, keeping the earlier file's conditions this run did not fly (a second run adds
a condition to the same --out; a condition flown again replaces its rows; a landings.csv that is not a
landings table is replaced, with a warning when the run starts). Re-running an interrupted evaluation with the
same settings reuses the landings already flown. One run at a time per --out: a second one started on the same
directory exits with status 2 naming the run that holds it (<out>/.evaluate.lock, removed at the end). A
worker process that dies (killed, out of memory) stops the run with one line and status 1; the landings flown
so far are kept for the re-run. Workers end with the evaluate process, even a SIGKILLed one.
"""
from __future__ import annotations

import csv
import functools
import dataclasses
import json
import logging
import math
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from assist_common.atomic import CsvLog, atomic_path, truncate_csv, write_text_atomic
from assist_sim.core.arducopter import FLIGHT_CONTROLLERS
from assist_sim.core.config import WorldConfig
from assist_sim.cues import CueConfig
from assist_sim.pilots import PILOT_NAMES

from assist_bags.bagio import BagError
from .landing_bags import record_landing
from .cluster import (DirectoryBusy, RayUnreachable, WorkerDied, WorkerPool, connect_ray, cpu_cores, exit_worker_died,
                      hold_directory)
from assist_common.settings import check_settings, parse_command, setting
from .env import EnvConfig, LandingAssistEnv, run_episode
from .episodes_plan import landing_seeds
from assist_perception.latent import make_latent_fn
from assist_policy.policy_core import default_model_path
from assist_policy.rules import RULES, Rule, rule_fields, switched
from assist_policy.scripted import LEAD_S, NEAREST_PAD_VARIANTS, ScriptedConfig, ScriptedOracle, make_nearest_pad
from assist_policy.actor import load_actor, run_actor

log = logging.getLogger(__name__)

CONDITIONS = ('unassisted', 'latent', 'oracle', 'end_to_end')
# hand-written assistants (reference only): the oracle script and every named nearest-pad teacher
# (scripted.NEAREST_PAD_VARIANTS: _yield yields to a held key, _gentle does not hurry the pilot's descent)
BASELINES = ('scripted_oracle', 'scripted_oracle_lead', *(f'scripted_{v}' for v in NEAREST_PAD_VARIANTS))
PAPER = {'unassisted': '0.67 +- 0.40', 'end_to_end': '0.37 +- 0.33', 'latent': '0.25 +- 0.15',
         'oracle': '0.10 +- 0.07'}


MAX_EVAL_SEED = 2**31 - 1 - 1000 * 1000 - 100_000     # landing seeds (seed + 1000 beta index + k) stay valid


def rule_option(r: Rule) -> dataclasses.Field:
    """evaluate's and evaluate_graph's option for a rule: a goal-agnostic one unset (None: as policy_node flies each
    mode), the others on."""
    return dataclasses.field(default=None if r.goal_agnostic else True)


def rule_help(r: Rule) -> str:
    """evaluate's --help line for a rule's option."""
    if not r.goal_agnostic:
        return (f'apply the {r.title} ({r.module}) to every assisted condition (on by default, as policy_node; false '
                f'with the other rules off: the bare actor, as the paper flew it)')
    return (f'apply the {r.title} ({r.module}) to the learned assistants (latent, oracle, end_to_end); unset: as '
            f'policy_node, on for latent and end_to_end, off for the oracle')


@dataclass
# the non-learned rules (a field per rule, assist_policy.rules.RULES), by default as policy_node flies each mode
# (false: the bare actor): the floor guard on; the goal-agnostic ones (None) on for latent and end_to_end, off for
# the oracle, which knows the goal
@rule_fields(rule_option, lambda r: bool | None)
class EvalArgs:
    """Command-line arguments of evaluate (every field is a --flag)."""

    out: str = setting('runs/eval', nonempty=True)
    conditions: tuple[str, ...] = setting(CONDITIONS, choices=CONDITIONS + BASELINES, min_len=1)
    alpha: float = setting(0.5, ge=0.0, le=1.0)
    betas: tuple[float, ...] = setting(tuple(np.round(np.arange(0.0, 1.0001, 0.05), 2).tolist()), ge=0.0, le=1.0,
                                       min_len=1)
    landings: int = setting(40, ge=1, le=100_000)        # 0 would replace an existing landings.csv with nothing
    seed: int = setting(2024, ge=0, le=MAX_EVAL_SEED)
    latent_model: str = ''
    oracle_model: str = ''
    end_to_end_model: str = ''
    encoder_path: str = ''
    max_episode_s: float = setting(60.0, gt=0.0, le=3600.0)
    plot: bool = True
    pilot: str = setting('paper', choices=PILOT_NAMES)
    from_csv: tuple[str, ...] = ()
    record_dir: str = ''
    workers: int = setting(0, ge=0, le=1024)      # 0: one per CPU core (a short run: fewer, see worker_count)
    flight_controller: str = setting('ideal', choices=FLIGHT_CONTROLLERS)
    world_config: str = ''                         # YAML of WorldConfig fields (e.g. the SITL start); '' = defaults
    ray: str = ''                                  # '' local processes; 'auto' a local Ray instance; or an address
    cues: bool = False                             # the assistant's intent shown to the pilots (assist_sim.cues)
    cue_trust: float = setting(1.0, ge=0.0, le=1.0)   # ... who read it in this share of their landings

# Settings that change how a run is carried out, not which landings it flies (not part of the resume key).
RUN_ONLY = ('out', 'plot', 'workers', 'ray')


HELP = {
    'out': 'output directory (landings.csv, summary.csv, error_vs_beta.png)',
    'conditions': 'any of unassisted latent oracle end_to_end (assistants without a model are skipped); '
                  'reference baselines: ' + ' '.join(BASELINES),
    'betas': 'pilot skills to test (paper: 0 to 1 in steps of 0.05)',
    'landings': 'landings per beta and condition (paper: 40)',
    'latent_model': 'actor file (default: models/td3_latent_actor.pt)',
    'oracle_model': 'actor file (default: models/td3_oracle_actor.pt)',
    'end_to_end_model': 'actor file (default: models/td3_end_to_end_actor.pt)',
    'encoder_path': 'CM-VAE weights for the latent condition (default: the shipped model)',
    'pilot': 'simulated pilot: paper (the reference), a family of assist_sim.pilots, mix (a held-out family '
             'per landing), approach_mix (glide or low_flyer per landing) or train_mix (a training family per '
             'landing)',
    **{r.field: rule_help(r) for r in RULES},
    'from_csv': 'fly nothing: combine the landings.csv files of earlier runs (e.g. one condition split '
                'over processes by --betas; a landing in a later file replaces the same condition, beta '
                'and seed in an earlier one) into one table, summary.csv and plot',
    'ray': 'fly the landings as tasks on a Ray cluster at this address (ray://HOST:10001 or HOST:6379; every '
           'node needs this workspace installed), or auto to start a local Ray instance; empty: local processes '
           '(--workers). Needs the optional ray package',
    'workers': 'processes flying landings side by side (0: one per CPU core, one per 8 landings for a short run); '
               'every landing is flown from its own seed, so the rows are those of a one-process run',
    'flight_controller': 'the plant that follows the velocity commands: ideal (the sim\'s own velocity loop) or '
                         'arducopter (ArduCopter GUIDED as the bridge flies it: assist_sim.core.arducopter, with '
                         'the touchdown envelope; the camera leans with the airframe and the encoder levels it)',
    'world_config': 'YAML file of assist_sim WorldConfig fields for the landing world (sim_node\'s world_config), '
                    'e.g. assist_sim/config/world_sitl_start.yaml: every landing starts where the SITL landing '
                    'series starts (over the start spot at take-off altitude); --flight-controller still applies',
    'cues': 'show the pilots the assistant\'s intent, as the pilot station does (the pad its command steers to, '
            'the descend/hold light: assist_policy.intent), and let them read it (assist_sim.cues); the assisted '
            'conditions are named <condition>+cues',
    'cue_trust': 'with --cues: the chance per landing that the pilot reads the cues (0: pilots who ignore them)',
    'record_dir': 'save every landing as a rosbag2 bag (the graph\'s topics and types) in this directory, '
                  'named <condition>_beta<beta>_seed<seed>: replay_assist / plot_flight take any of them',
}

LANDING_FIELDS = ['condition', 'beta', 'seed', 'scene_seed', 'goal_index', 'landed_index', 'nearest_index',
                  'aimed_index', 'error_m', 'nearest_error_m', 'outcome', 'success', 'crash', 'duration_s',
                  'active_fraction', 'pilot', *(f'{r.flag}_fraction' for r in RULES), 'wall_fraction',
                  'autopilot_landed', 'path_m']
# goal inference of an actor with a goal head (empty for the others): the share of steps whose estimate is nearest
# the pilot's goal pad at that step, over the landing and within each window of time to touchdown (s)
GOAL_WINDOWS_S = ((0.0, 1.0), (1.0, 2.0), (2.0, 4.0), (4.0, 8.0))
GOAL_FIELDS = ['goal_acc', *(f'goal_acc_{lo:g}_{hi:g}s' for lo, hi in GOAL_WINDOWS_S)]
LANDING_FIELDS += GOAL_FIELDS
_BOOL = {'True': True, 'False': False}


def read_landings(path: str | Path) -> dict[str, list[dict]]:
    """Rows of a landings.csv grouped by condition, typed as evaluate writes them; ValueError if malformed."""
    out: dict[str, list[dict]] = {}
    with open(path, newline='', encoding='utf-8') as fh:
        reader = csv.DictReader(fh)
        missing = {'condition', 'beta', 'goal_index', 'error_m', 'success', 'crash', 'outcome'} - set(
            reader.fieldnames or ())
        if missing:
            raise ValueError(f'{path}: not a landings.csv (missing columns {sorted(missing)})')
        for n, r in enumerate(reader, start=2):
            try:
                row = dict(r, beta=float(r['beta']), error_m=float(r['error_m']),
                           nearest_error_m=float(r.get('nearest_error_m') or 'nan'),
                           success=_BOOL[r['success']], crash=_BOOL[r['crash']],
                           active_fraction=float(r.get('active_fraction') or 0.0),
                           duration_s=float(r.get('duration_s') or 'nan'), path_m=float(r.get('path_m') or 'nan'),
                           goal_index=int(r['goal_index']),
                           autopilot_landed=_BOOL.get(r.get('autopilot_landed') or '', None),
                           **{k: None if r.get(k) in (None, '') else float(r[k]) for k in GOAL_FIELDS},
                           **{k: None if r.get(k) in (None, '') else int(r[k])
                              for k in ('seed', 'landed_index', 'nearest_index', 'aimed_index')})
            except (KeyError, ValueError) as exc:
                raise ValueError(f'{path}:{n}: bad row: {exc!r}') from exc
            out.setdefault(r['condition'], []).append(row)
    return out


class LandingLog:
    """landings.csv written crash-safely and resumably (see the module docstring)."""

    def __init__(self, out: Path, settings: dict):
        self.path, self.partial = out / 'landings.csv', out / 'landings.partial.csv'
        self.settings_file = out / 'landings.partial.json'
        self.done: dict[tuple, dict] = {}
        settings = json.loads(json.dumps(settings, sort_keys=True))     # tuples -> lists, as stored
        same = (self.partial.exists() and self.settings_file.exists()
                and json.loads(self.settings_file.read_text(encoding='utf-8')) == settings)
        if same:
            truncate_csv(self.partial, lambda row: True)      # drops a row torn by a kill
            self.done = {(c, r['beta'], r['seed']): r for c, rows in read_landings(self.partial).items()
                         for r in rows}
            log.info('resuming: %d landings already flown in %s', len(self.done), self.partial)
        else:
            self.partial.unlink(missing_ok=True)
            write_text_atomic(self.settings_file, json.dumps(settings, sort_keys=True))
        self.csv = CsvLog(self.partial, LANDING_FIELDS)
        # a landings.csv of an earlier run into this --out: its other conditions are kept at commit
        self.earlier: dict[str, list[dict]] = {}
        if self.path.exists():
            try:
                self.earlier = read_landings(self.path)
            except (ValueError, KeyError, UnicodeDecodeError) as exc:
                log.warning('%s is not a landings table (%s): this run replaces it when it ends', self.path, exc)

    def flown(self, condition: str, beta: float, seed: int) -> dict | None:
        """The row of a landing an interrupted run already flew, or None."""
        return self.done.get((condition, beta, seed))

    def write(self, row: dict) -> None:
        """Append one landing (flushed)."""
        self.csv.write(row)

    def sync(self) -> None:
        """Make the landings written so far durable."""
        self.csv.sync()

    def close(self) -> None:
        """Close the partial file (kept for a resume)."""
        self.csv.close()

    def commit(self, rows_by_cond: dict[str, list[dict]]) -> dict[str, list[dict]]:
        """Write landings.csv: this run's conditions, and those of an earlier landings.csv in the same --out
        that this run did not fly (kept as they were; a condition flown again is replaced). Drops the partial
        files; returns the table written (empty when nothing was flown: an earlier landings.csv stays as it is)."""
        self.close()
        table: dict[str, list[dict]] = {}
        if rows_by_cond:
            kept = {c: rows for c, rows in self.earlier.items() if c not in rows_by_cond}
            if kept:
                log.info('%s: kept the earlier landings of %s', self.path, ', '.join(kept))
            table = {**kept, **rows_by_cond}
            write_landings(self.path, table)
        self.partial.unlink(missing_ok=True)
        self.settings_file.unlink(missing_ok=True)
        return table


def write_landings(path: Path, rows_by_cond: dict[str, list[dict]]) -> None:
    """Write a landings.csv in one atomic step."""
    with atomic_path(path) as tmp, open(tmp, 'w', newline='', encoding='utf-8') as fh:
        w = csv.DictWriter(fh, fieldnames=LANDING_FIELDS, extrasaction='ignore')
        w.writeheader()
        for rows in rows_by_cond.values():
            w.writerows(rows)


def make_policy(condition: str, model: str, encoder_path: str, max_episode_s: float, alpha: float,
                pilot: str = 'paper', rules: Mapping[str, Any] | None = None,
                flight_controller: str = 'ideal', world_config: str = '', cues: CueConfig | None = None):
    """(env, policy) for one condition; policy(obs) -> raw action, None for unassisted.

    `rules`: the non-learned rules that fly, by settings field (assist_policy.rules.RULES) with their settings
    (None: the defaults); the others are off, and the scripted references fly only the floor guard. `cues`: the
    assistant's intent is shown to the pilots, who read it so (None: not shown; never without an assistant)."""
    given = dict(rules or {})
    unknown = sorted(set(given) - {r.field for r in RULES})
    if unknown:
        raise ValueError(f'no rule(s) {unknown}: rules are {", ".join(r.field for r in RULES)}')
    flying = {r.field: switched(r, True, given[r.field]) if r.field in given else switched(r, False) for r in RULES}
    world = WorldConfig.from_yaml(world_config) if world_config else WorldConfig()
    world.flight_controller = flight_controller
    if condition == 'unassisted':
        return LandingAssistEnv(EnvConfig(condition='none', alpha=alpha, max_episode_s=max_episode_s,
                                          pilot_family=pilot, world=world)), None
    if condition in BASELINES:
        env = LandingAssistEnv(EnvConfig(condition='oracle', alpha=alpha, max_episode_s=max_episode_s,
                                         pilot_family=pilot, safety=flying['safety'], world=world,
                                         cues=cues is not None, pilot_cues=cues or CueConfig()))
        script = (ScriptedOracle() if condition == 'scripted_oracle' else
                  ScriptedOracle(ScriptedConfig(lead_s=LEAD_S)) if condition == 'scripted_oracle_lead' else
                  make_nearest_pad(condition[len('scripted_'):]))
        return env, lambda obs: script.raw_action(env)
    path = Path(model) if model else default_model_path(condition)
    actor, meta = load_actor(path)
    cfg = EnvConfig(condition=condition, alpha=alpha, max_episode_s=max_episode_s,
                    max_speed=tuple(meta.get('max_speed', (1.0, 1.0, 0.6))),
                    latent_dim=int(meta.get('latent_dim', 0)), pilot_family=pilot, **flying, world=world,
                    feature_lags_s=tuple(meta['feature_lags_s']), memory_displacement=meta['memory_displacement'],
                    history_s=meta['history_s'], history_step_s=meta['history_step_s'],
                    cues=cues is not None, pilot_cues=cues or CueConfig())
    if condition == 'latent':
        latent_fn, dim = make_latent_fn(encoder_path or None)
        if dim != cfg.latent_dim:
            raise ValueError(f'{path}: trained on a {cfg.latent_dim}-d latent, the encoder gives {dim}')
        env = LandingAssistEnv(cfg, latent_fn=latent_fn)
    else:
        env = LandingAssistEnv(cfg)

    if meta['goal_head']:
        return env, GoalHeadPolicy(env, actor)

    @torch.no_grad()
    def policy(obs: np.ndarray) -> np.ndarray:
        return actor(torch.as_tensor(obs).unsqueeze(0))[0].numpy().astype(float)
    return env, policy


class GoalHeadPolicy:
    """An actor with a goal head flown in `env`: the raw action; its goal estimate goes to the env for the step
    (``env.learned_goal``: the intent, as policy_node's core hands it on, and the env's ``goal_trace``)."""

    def __init__(self, env: LandingAssistEnv, actor: torch.nn.Module):
        self.env, self.actor = env, actor

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The raw action for `obs`."""
        action, self.env.learned_goal = run_actor(self.actor, obs, self.env.world.state.position)
        return action


def goal_inference(trace: list[tuple[float, bool]], duration_s: float) -> dict[str, float | str]:
    """GOAL_FIELDS of a landing from its goal trace (env.goal_trace: time, estimate nearest the goal pad); '' where
    no step falls (every field '' for an assistant without a learned goal)."""
    hits = [(duration_s - t, ok) for t, ok in trace]
    out: dict[str, float | str] = {'goal_acc': round(float(np.mean([ok for _, ok in hits])), 3) if hits else ''}
    for (lo, hi), name in zip(GOAL_WINDOWS_S, GOAL_FIELDS[1:]):
        inside = [ok for left, ok in hits if lo <= left < hi]
        out[name] = round(float(np.mean(inside)), 3) if inside else ''
    return out


def run_landing(env: LandingAssistEnv, policy, seed: int, beta: float) -> dict:
    """One landing with the given seed and pilot skill; the result row."""
    res = run_episode(env, policy, seed, {'beta': beta})
    return {'beta': beta, 'seed': seed, 'scene_seed': res['scene_seed'], 'goal_index': res['goal_index'],
            'landed_index': res['landed_index'], 'nearest_index': res['nearest_index'],
            'aimed_index': res['aimed_index'],
            'error_m': round(float(res['error_m']), 4), 'nearest_error_m': round(float(res['nearest_error_m']), 4),
            'outcome': res['outcome'], 'success': bool(res['success']), 'crash': bool(res['crash']),
            'duration_s': round(float(res['duration_s']), 2), 'active_fraction': round(res['active_fraction'], 3),
            'pilot': res['pilot'], **{f'{r.flag}_fraction': round(res[f'{r.flag}_fraction'], 3) for r in RULES},
            'wall_fraction': round(res['wall_fraction'], 3),
            'autopilot_landed': '' if res.get('autopilot_landed') is None else bool(res['autopilot_landed']),
            'path_m': round(float(res['path_m']), 3),
            **goal_inference(env.goal_trace, float(res['duration_s']))}


def summarize(rows: list[dict]) -> dict:
    """Table I statistics of a set of landing rows."""
    err = np.array([r['error_m'] for r in rows], dtype=float)
    landed_clean = [r['outcome'] in ('success', 'wrong_pad') for r in rows]
    # the pilot's first goal estimate was nearest another pad than its goal (it set off for the wrong one)
    known_aim = any(r.get('aimed_index') not in (None, '') for r in rows)   # older CSVs lack the column
    misaimed = [r.get('aimed_index') not in (None, '') and int(r['aimed_index']) != int(r['goal_index'])
                for r in rows]
    return {'n': len(rows), 'error_mean': float(err.mean()), 'error_std': float(err.std()),
            'error_median': float(np.median(err)),
            'specified_success': float(np.mean([r['success'] for r in rows])),
            'nearest_success': float(np.mean([c and r['landed_index'] == r['nearest_index']
                                              for c, r in zip(landed_clean, rows)])),
            'crash_rate': float(np.mean([r['crash'] for r in rows])),
            'landed_on_goal': float(np.mean([r['landed_index'] is not None and int(r['landed_index']) ==
                                             int(r['goal_index']) for r in rows])),
            'active_fraction': float(np.mean([r['active_fraction'] for r in rows])),
            'misaimed': float(np.mean(misaimed)) if known_aim else float('nan'),
            'misaimed_success': (float(np.mean([r['success'] for r, m in zip(rows, misaimed) if m]))
                                 if any(misaimed) else float('nan')),
            **{k: float(np.mean(vals)) if (vals := [r[k] for r in rows if r.get(k) not in (None, '')])
               else float('nan') for k in GOAL_FIELDS},
            # arducopter plant: of the touchdowns, the share its land detector declared (nan on the ideal plant)
            'autopilot_landed': (float(np.mean([bool(r['autopilot_landed']) for r in checked]))
                                 if (checked := [r for r in rows if r.get('autopilot_landed') not in (None, '')])
                                 else float('nan'))}


def mean_se(d: np.ndarray) -> tuple[float, float]:
    """Mean of paired differences `d` and its standard error (nan for fewer than two)."""
    d = np.asarray(d, dtype=float)
    return float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float('nan')


def paired_vs_unassisted(rows_by_cond: dict[str, list[dict]], worse_m: float = 0.25) -> dict[str, dict]:
    """Per condition, against unassisted on the same landings (beta, seed): error and crash differences.

    `delta_error` is the mean of (error - unassisted error) with its standard error `delta_se`;
    `worse` the share of landings more than `worse_m` worse than unassisted (a new crash counts as worse),
    `new_crash` the share that crash where the unassisted pilot did not.
    """
    base = {(r['beta'], r.get('seed')): r for r in rows_by_cond.get('unassisted', [])}
    out = {}
    for cond, rows in rows_by_cond.items():
        pairs = [(r, base[(r['beta'], r.get('seed'))]) for r in rows
                 if cond != 'unassisted' and (r['beta'], r.get('seed')) in base]
        if not pairs:
            continue
        d = np.array([r['error_m'] - b['error_m'] for r, b in pairs])
        new_crash = np.array([r['crash'] and not b['crash'] for r, b in pairs])
        delta, se = mean_se(d)
        out[cond] = {'n': len(pairs), 'delta_error': delta, 'delta_se': se,
                     'worse': float(np.mean((d > worse_m) | new_crash)), 'new_crash': float(new_crash.mean())}
    return out


def format_paired(paired: dict[str, dict]) -> str:
    """Text table of paired_vs_unassisted."""
    lines = [f'{"vs unassisted, same landings":<28} {"n":>4} {"d error m (+- se)":>18} {"worse >0.25m":>12} '
             f'{"new crash":>9}']
    for cond, p in paired.items():
        lines.append(f'{cond:<28} {p["n"]:>4} {p["delta_error"]:>+9.3f} +- {p["delta_se"]:<5.3f} '
                     f'{100 * p["worse"]:>11.1f}% {100 * p["new_crash"]:>8.1f}%')
    return '\n'.join(lines)


def _pct(x: float) -> str:
    """A share as a 6-wide percentage, or n/a when undefined (e.g. no misaimed landings)."""
    return f'{"n/a":>6}' if not np.isfinite(x) else f'{100 * x:>5.1f}%'


def format_table(summary: dict[str, dict]) -> str:
    """Fixed-width text table of per-condition summaries (paper: the paper's value for the assistant, rules aside)."""
    w = max([20, *map(len, summary)])
    head = (f'{"condition":<{w}} {"n":>4} {"error m (mean+-std)":>20} {"median":>7} {"spec.succ":>9} '
            f'{"near.succ":>9} {"crash":>6} {"on goal":>7} {"assist%":>7} {"misaim":>6} {"->goal":>6}  paper')
    lines = [head, '-' * len(head)]
    for cond, s in summary.items():
        lines.append(f'{cond:<{w}} {s["n"]:>4} {s["error_mean"]:>11.3f} +- {s["error_std"]:<5.3f} '
                     f'{s["error_median"]:>7.3f} {100 * s["specified_success"]:>8.1f}% '
                     f'{100 * s["nearest_success"]:>8.1f}% {100 * s["crash_rate"]:>5.1f}% '
                     f'{100 * s["landed_on_goal"]:>6.1f}% {100 * s["active_fraction"]:>6.1f}% '
                     f'{_pct(s["misaimed"])} {_pct(s["misaimed_success"])}  '
                     f'{PAPER.get(cond.split("+")[0], "")}')
    return '\n'.join(lines)


def plot(rows_by_cond: dict[str, list[dict]], path: Path) -> None:
    """Against pilot skill beta, per condition: the landing error's median with its inter-quartile band (the
    error is heavy-tailed, so a mean +- std band would dip below zero), goal-pad success and crash rates."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, (ax, ax_s, ax_c) = plt.subplots(3, 1, figsize=(6.4, 7.2), sharex=True,
                                         gridspec_kw={'height_ratios': [2, 1, 1]})
    for cond, rows in rows_by_cond.items():
        betas = sorted({r['beta'] for r in rows})
        by_beta = [[r for r in rows if r['beta'] == b] for b in betas]
        q1, med, q3 = np.array([np.percentile([r['error_m'] for r in rs], [25, 50, 75]) for rs in by_beta]).T
        line, = ax.plot(betas, med, marker='o', ms=3, label=cond)
        ax.fill_between(betas, q1, q3, alpha=0.15, color=line.get_color())
        ax_s.plot(betas, [100 * np.mean([r['success'] for r in rs]) for rs in by_beta], marker='o', ms=3,
                  color=line.get_color())
        ax_c.plot(betas, [100 * np.mean([r['crash'] for r in rs]) for rs in by_beta], marker='o', ms=3,
                  color=line.get_color())
    ax.set_ylabel('landing error (m)\nmedian, IQR band')
    ax.set_ylim(bottom=0)
    ax_s.set_ylabel('goal-pad\nsuccess (%)')
    ax_c.set_ylabel('crash (%)')
    for a in (ax_s, ax_c):
        a.set_ylim(-3, 103)
    ax_c.set_xlabel('pilot skill beta (alpha = 0.5)')
    for a in (ax, ax_s, ax_c):
        a.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)


def evaluate(args: EvalArgs) -> dict[str, dict]:
    """Run the experiment; write CSVs and the plot; return per-condition summaries (SettingsError: a bad value)."""
    check_settings(args)
    if args.pilot not in PILOT_NAMES:
        raise ValueError(f'unknown pilot {args.pilot!r}; choose from {", ".join(PILOT_NAMES)}')
    if args.world_config:           # unreadable or with an unknown field: refused before anything flies
        try:
            WorldConfig.from_yaml(args.world_config)
        except (OSError, ValueError, TypeError, yaml.YAMLError) as exc:
            raise ValueError(f'--world-config {args.world_config}: {exc}') from None
    out = Path(args.out)
    rows_by_cond: dict[str, list[dict]] = {}
    for path in args.from_csv:      # a landing (condition, beta, seed) seen again replaces the earlier one
        for cond, rows in read_landings(path).items():
            merged = {(r['beta'], r['seed']): r for r in rows_by_cond.get(cond, [])}
            merged.update({(r['beta'], r['seed']): r for r in rows})
            rows_by_cond[cond] = sorted(merged.values(), key=lambda r: (r['beta'], r['seed'] or 0))
    for cond in () if args.from_csv else args.conditions:
        if cond not in CONDITIONS + BASELINES:
            raise ValueError(f'unknown condition {cond!r}; choose from {CONDITIONS + BASELINES}')
    # one run per directory: another one's LandingLog would remove or rewrite this one's landings as it flies
    with hold_directory(out, 'evaluate', 'wait for it to end, or choose another --out'):
        if args.ray and not args.from_csv:
            connect_ray(args.ray)           # an address that is not Ray: refused before the landings file is touched
        results = None if args.from_csv else LandingLog(out, {k: v for k, v in dataclasses.asdict(args).items()
                                                              if k not in RUN_ONLY})
        try:
            if not args.from_csv:
                rows_by_cond.update(fly_plan(args, results))
        finally:
            if results is not None:
                results.close()
        if results is not None:
            rows_by_cond = results.commit(rows_by_cond)
        elif rows_by_cond:
            write_landings(out / 'landings.csv', rows_by_cond)
        return write_results(out, rows_by_cond, args.plot)


@dataclasses.dataclass(frozen=True)
class PlannedLanding:
    """One landing of the plan: condition `cond` (row name `name`) at pilot skill `beta` from `seed`."""

    cond: str
    name: str
    beta: float
    seed: int


def plan_tasks(args: EvalArgs) -> list[PlannedLanding]:
    """Every landing of a run in the one-process order: condition, then beta, then landing (`landing_seeds`)."""
    tasks = []
    for cond in args.conditions:
        name = condition_name(cond, rules_flying(args, cond), cues_shown(args, cond))
        tasks += [PlannedLanding(cond, name, beta, s)
                  for s, beta in landing_seeds(args.seed, args.betas, args.landings)]
    return tasks


class LandingFlyer:
    """Flies landings in this process: one env and assistant per condition, made on its first landing."""

    def __init__(self, args: EvalArgs) -> None:
        self.args = args
        self.made: dict[str, tuple] = {}

    def fly(self, task: PlannedLanding) -> dict:
        """The landing's row (ValueError when the condition's assistant cannot be made, e.g. no model)."""
        a = self.args
        if task.cond not in self.made:
            model = getattr(a, f'{task.cond}_model', '') if task.cond in CONDITIONS[1:] else ''
            flying = {r.field: None for r, on in rules_flying(a, task.cond).items() if on}
            cues = CueConfig(trust=a.cue_trust) if cues_shown(a, task.cond) else None
            self.made[task.cond] = make_policy(task.cond, model, a.encoder_path, a.max_episode_s, a.alpha,
                                               pilot=a.pilot, rules=flying, flight_controller=a.flight_controller,
                                               world_config=a.world_config, cues=cues)
        env, policy = self.made[task.cond]
        row = (record_landing(run_landing, env, policy, task.seed, task.beta, task.name, a.record_dir)
               if a.record_dir else run_landing(env, policy, task.seed, task.beta))
        row['condition'] = task.name
        return row

    def close(self) -> None:
        """Close every env this flyer made."""
        for env, _ in self.made.values():
            env.close()
        self.made.clear()


def worker_flyer(args: EvalArgs) -> LandingFlyer:
    """A pool worker's flyer: one torch thread in the worker process (the workers are the parallelism)."""
    torch.set_num_threads(1)
    return LandingFlyer(args)


# A worker process spends ~5 s importing torch and building its envs (about three landings' worth): with
# `--workers 0` a run gets another process for every this many landings, up to one per CPU core.
LANDINGS_PER_AUTO_WORKER = 8


def worker_count(requested: int, landings: int) -> int:
    """Processes to fly `landings` with: `requested` (never more than the landings), or for 0 one per CPU core,
    fewer for a short run (LANDINGS_PER_AUTO_WORKER)."""
    if requested:
        return max(1, min(requested, landings))
    return max(1, min(cpu_cores(), landings // LANDINGS_PER_AUTO_WORKER))


def fly_plan(args: EvalArgs, results: LandingLog) -> dict[str, list[dict]]:
    """Fly every landing of the plan not already in `results` (each written there as it lands), on
    `args.workers` processes, with a progress bar; the rows per condition in plan order. A condition whose
    assistant cannot be made is skipped with a warning."""
    plan = plan_tasks(args)
    rows = {t: results.flown(t.name, t.beta, t.seed) for t in plan}
    todo = [t for t in plan if rows[t] is None]
    skipped: set[str] = set()
    workers = worker_count(args.workers, len(todo))
    t0 = time.time()
    last_landed: dict[str, float] = {}      # condition -> when its last landing landed (s after t0)
    bar = tqdm(total=len(plan), initial=len(plan) - len(todo), desc='evaluate', unit='landing', file=sys.stderr,
               mininterval=1.0, dynamic_ncols=False, disable=None)

    def landed(task: PlannedLanding, row: dict | None, exc: Exception | None) -> None:
        if exc is not None:
            if task.cond not in skipped:
                log.warning('skipping %s: %s', task.cond, exc)
            skipped.add(task.cond)
            return
        rows[task] = row
        results.write(row)
        last_landed[task.cond] = time.time() - t0
        bar.update(1)

    with logging_redirect_tqdm():
        try:
            if workers == 1 and not args.ray:
                flyer = LandingFlyer(args)
                try:
                    for task in todo:
                        if task.cond in skipped:
                            continue
                        try:
                            row = flyer.fly(task)
                        except ValueError as exc:
                            landed(task, None, exc)
                            continue
                        landed(task, row, None)
                finally:
                    flyer.close()
            elif todo:
                with WorkerPool(functools.partial(worker_flyer, args), 0 if args.ray else workers, args.ray) as pool:
                    handles = {pool.submit(t): t for t in todo}
                    try:
                        for handle in pool.completed(handles):
                            try:
                                row, exc = pool.result(handle), None
                            except ValueError as err:       # the condition's assistant cannot be made
                                row, exc = None, err
                            landed(handles[handle], row, exc)
                    except WorkerDied as exc:
                        raise WorkerDied(f'{exc}; the landings flown so far are kept in {results.partial}: '
                                         're-running the same command resumes') from None
                    except BaseException:
                        for handle in handles:
                            pool.cancel(handle)
                        raise
        finally:
            results.sync()
            bar.close()
    out: dict[str, list[dict]] = {}
    for task in plan:
        if task.cond not in skipped and rows[task] is not None:
            out.setdefault(task.name, []).append(rows[task])
    for cond, seconds in last_landed.items():
        log.info('%s: last landing landed %.0f s after the start', cond, seconds)
    return out


def write_results(out: Path, rows_by_cond: dict[str, list[dict]], with_plot: bool = True) -> dict[str, dict]:
    """summary.csv, error_vs_beta.png and paired.txt of a run's landings in `out`; the per-condition summaries."""
    summary = {c: summarize(r) for c, r in rows_by_cond.items()}
    with atomic_path(out / 'summary.csv') as tmp, open(tmp, 'w', newline='', encoding='utf-8') as fh:
        w = csv.writer(fh)
        keys = ['n', 'error_mean', 'error_std', 'error_median', 'specified_success', 'nearest_success',
                'crash_rate', 'landed_on_goal', 'active_fraction', 'misaimed', 'misaimed_success']
        if any(math.isfinite(s['goal_acc']) for s in summary.values()):     # an actor with a goal head flew
            keys += GOAL_FIELDS
        w.writerow(['condition'] + keys)
        for c, s in summary.items():
            w.writerow([c] + [round(s[k], 4) for k in keys])
    if with_plot and rows_by_cond:
        plot(rows_by_cond, out / 'error_vs_beta.png')
    paired = paired_vs_unassisted(rows_by_cond)
    if paired:
        write_text_atomic(out / 'paired.txt', format_paired(paired) + '\n')
    return summary


def condition_name(cond: str, flying: Mapping[Rule, bool], cues: bool = False) -> str:
    """A condition's row name: cond, then +<flag> for each rule that flies with it (registry order), +cues when
    the pilots see the assistant's intent."""
    return cond + ''.join(f'+{r.flag}' for r, on in flying.items() if on) + ('+cues' if cues else '')


def cues_shown(args: Any, cond: str) -> bool:
    """Whether the pilots of `cond` see the assistant's intent (--cues; never without an assistant)."""
    return bool(getattr(args, 'cues', False)) and cond != 'unassisted'


def rules_flying(args: Any, cond: str) -> dict[Rule, bool]:
    """Whether each rule flies with `cond` for options `args` (a bool or None per rule's settings field): the
    floor guard with every assisted condition as asked; a goal-agnostic rule with the learned assistants only, as
    asked, else (None) as policy_node's default for the mode (on for latent and end_to_end, off for the oracle)."""
    out = {}
    for r in RULES:
        asked = getattr(args, r.field)
        if cond == 'unassisted' or (r.goal_agnostic and cond not in CONDITIONS[1:]):
            out[r] = False
        else:
            out[r] = bool(asked) if asked is not None else r.default_on(cond)
    return out


def main(argv: list[str] | None = None) -> int:
    """Console entry point: run, print the table."""
    torch.set_num_threads(1)
    cmd = parse_command(EvalArgs, 'evaluate', __doc__, HELP, argv)   # a bad value: one error line, exit 2, nothing run
    args = cmd.settings
    try:
        summary = evaluate(args)
    except (DirectoryBusy, RayUnreachable) as exc:      # the --out or --ray given cannot be used now
        print(f'error: {exc}', file=sys.stderr)
        return 2
    except WorkerDied as exc:
        exit_worker_died(f'error: {exc}')
    except (OSError, ValueError, BagError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    if not summary:
        print('no condition could be evaluated', file=sys.stderr)
        return 1
    if args.from_csv:
        print(f'combined from {", ".join(args.from_csv)}')
    else:
        state = {True: 'on', False: 'off', None: 'on (oracle: off)'}
        print(f'pilot {args.pilot}, '
              + ''.join(f'{r.title} {state[getattr(args, r.field)]}, ' for r in RULES)
              + f'alpha {args.alpha}, '
              f'betas {args.betas[0]}..{args.betas[-1]} ({len(args.betas)}), '
              f'{args.landings} landings each, seed {args.seed}')
    print_results(summary, args.out)
    return 0


def format_goal_inference(summary: dict[str, dict]) -> str:
    """The goal-inference table of the conditions whose actor has a goal head ('' when none has)."""
    rows = [(c, s) for c, s in summary.items() if math.isfinite(s.get('goal_acc', float('nan')))]
    if not rows:
        return ''
    head = ['goal inference', 'all steps', *(f'{lo:g}-{hi:g} s to touchdown' for lo, hi in GOAL_WINDOWS_S)]
    lines = [' | '.join(head)]
    for c, s in rows:
        lines.append(' | '.join([c, *('-' if not math.isfinite(s[k]) else f'{100 * s[k]:.1f} %' for k in GOAL_FIELDS)]))
    return '\n'.join(lines)


def print_results(summary: dict[str, dict], out: str, extra: str = '') -> None:
    """Print the table, the goal inference (actors with a goal head), the paired comparison (paired.txt, when
    written) and what was written to `out`."""
    print(format_table(summary))
    goal = format_goal_inference(summary)
    if goal:
        print(goal)
    paired = Path(out) / 'paired.txt'
    if paired.exists():
        print(paired.read_text(encoding='utf-8'), end='')
    print(f'written: {out}/landings.csv, summary.csv, error_vs_beta.png{extra}')


if __name__ == '__main__':
    sys.exit(main())
