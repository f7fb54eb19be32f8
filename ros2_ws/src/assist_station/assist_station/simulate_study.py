"""simulate_study: the user study end to end with simulated participants flying the real station.

    simulate_study --participants 12 --out study_sim          # the shipped study file (16 landings per block)
    simulate_study --participants 2 --landings-per-block 3 --practice 1 --out /tmp/s --browser-participants 1
    simulate_study --participants 6 --study config/study_cues.yaml --out study_cues   # + the assisted_cues block
    analyze_study study_sim/* --out study_sim_analysis

Starts the node graph a lab runs for the study (sim_node, encoder_node and policy_node in the study
file's assistant mode, pilot_station with the study file) on a private ROS_DOMAIN_ID and lets each
simulated participant (assist_station.participant: a pilot family with a skill drawn per participant,
questionnaire answers scripted from skill and performance, a ``cue_trust`` drawn from ``--cue-trust``: the
chance per landing of reading the station's intent cues in an assisted_cues block) go through the whole
protocol over the station's WebSocket, one after another. With ``--browser-participants M`` the first M participants
use the station page in headless Chromium instead (the page's own forms, buttons and keyboard
handling; ``make browser`` installs Chromium). Each participant's directory is DIR/<ID> (landings.csv,
survey.json, protocol.log, bags/), with ``simulated_participant.json`` saying who the simulated
participant was; the study file used, the node logs and a summary are under DIR/.simulation/.
A participant already done in DIR is skipped, one half done resumes where it stopped.
"""
from __future__ import annotations

import asyncio
import dataclasses
import json
import logging
import signal
import socket
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from assist_common.atomic import write_text_atomic
from assist_common.settings import SettingsError
from assist_common.settings import parse_command, setting
from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from .participant import CUE_TRUST, DEFAULT_FAMILIES, Participant, Profile, draw_profiles
from .study import PARTICIPANT_ID, StudyConfig, StudyError

log = logging.getLogger('simulate_study')
STATION_STARTUP_S = 60.0


@dataclass
class SimulateArgs:
    """Command-line arguments of simulate_study (every field is a --flag)."""

    out: str = setting('study_sim', nonempty=True)
    participants: int = setting(12, ge=1, le=500)
    study: str = ''
    landings_per_block: int = setting(0, ge=0, le=200)
    practice: int = setting(2, ge=0, le=100)
    families: tuple[str, ...] = setting(DEFAULT_FAMILIES, min_len=1)
    seed: int = setting(0, ge=0, le=2 ** 31 - 1)
    real_time_factor: float = setting(2.0, gt=0.0, le=20.0)
    max_landing_s: float = setting(0.0, ge=0.0, le=3600.0)
    browser_participants: int = setting(0, ge=0, le=500)
    record_bags: bool = True
    domain_id: int = setting(0, ge=0, le=232)
    id_prefix: str = setting('S', nonempty=True)
    only: tuple[str, ...] = ()
    cue_trust: tuple[float, float] = setting(CUE_TRUST, ge=0.0, le=1.0)

    def check_relations(self) -> None:
        """The participant IDs --id-prefix and --participants make are IDs the study accepts; --cue-trust is a
        range (low, high)."""
        try:
            participant_ids(self)
        except StudyError as exc:
            raise SettingsError(f'--id-prefix {exc}') from None
        if self.cue_trust[0] > self.cue_trust[1]:
            raise SettingsError(f'--cue-trust: the low end {self.cue_trust[0]:g} is above the high end '
                                f'{self.cue_trust[1]:g}')


def participant_ids(args: SimulateArgs) -> list[str]:
    """The simulated participants' IDs, <prefix>01, <prefix>02, ...; StudyError unless each is a participant ID
    (1-32 letters, digits, _ or -, starting with a letter or digit: never a path, so each directory stays
    under --out)."""
    ids = [f'{args.id_prefix}{i + 1:02d}' for i in range(args.participants)]
    bad = [pid for pid in (ids[:1] + ids[-1:]) if not PARTICIPANT_ID.fullmatch(pid)]
    if bad:
        raise StudyError(f'{args.id_prefix!r} makes the participant ID {bad[0]!r}; participant IDs are 1-32 '
                         'letters, digits, _ or -, starting with a letter or digit')
    return ids


HELP = {
    'out': 'directory of the participants\' directories (created; existing participants resume or are skipped)',
    'participants': 'number of simulated participants',
    'study': 'study YAML file (default: the shipped config/study.yaml; config/study_cues.yaml adds the '
             'assisted_cues block)',
    'landings_per_block': 'fly only the first K landings of the study\'s sequence per block (0: all of them)',
    'practice': 'practice landings each participant flies at most (and the study file\'s practice_landings cap)',
    'families': 'pilot families of assist_sim.pilots, assigned to participants in turn',
    'seed': 'seed of the participants (skills, families, answers, pilots)',
    'real_time_factor': 'sim seconds per wall second (the graph must keep up: 2 on two cores)',
    'max_landing_s': 'a landing not done after this many sim seconds ends as a timeout (sim_node episode_timeout_s; '
                     'a quick dry run of the protocol); 0: the sim\'s own limit (90 s)',
    'browser_participants': 'the first N participants use the station page in headless Chromium',
    'record_bags': 'record a bag per landing (the study file\'s record_bags; false saves disk for big runs)',
    'domain_id': 'ROS_DOMAIN_ID of the graph (0: pick a free one)',
    'id_prefix': 'participant IDs are <prefix>01, <prefix>02, ... (odd numbers start unassisted); letters, digits, '
                 '_ or -, starting with a letter or digit, the IDs at most 32 characters',
    'only': 'fly only these participant IDs of the --participants drawn (e.g. a second graph sharing the work; '
            'give each run its own IDs)',
    'cue_trust': 'LOW HIGH: each participant\'s chance per landing of reading the intent cues (assisted_cues '
                 'blocks) is drawn uniformly in this range',
}


def shipped_study() -> Path:
    """The shipped study file: share/assist_station/config/study.yaml, else the source tree's config/study.yaml."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
        try:
            path = Path(get_package_share_directory('assist_station')) / 'config' / 'study.yaml'
            if path.is_file():
                return path
        except (PackageNotFoundError, LookupError, OSError, ValueError):   # not in an ament index
            pass
    except ImportError:
        pass
    return Path(__file__).resolve().parent.parent / 'config' / 'study.yaml'


def free_tcp_port() -> int:
    """A TCP port on 127.0.0.1 that nobody listens on right now."""
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def study_file(args: SimulateArgs, sim_dir: Path) -> tuple[StudyConfig, Path]:
    """The study file this run uses (the given or shipped one, cut to --landings-per-block / --practice)."""
    cfg, _ = StudyConfig.load(args.study or shipped_study())
    seq = cfg.sequence[:args.landings_per_block] if args.landings_per_block else cfg.sequence
    cfg = dataclasses.replace(cfg, sequence=tuple(seq), practice_landings=min(cfg.practice_landings, args.practice),
                              record_bags=cfg.record_bags and args.record_bags)
    path = sim_dir / 'study.yaml'
    import yaml
    text = '# study file of a simulated study (simulate_study)\n' + yaml.safe_dump(cfg.to_dict(), sort_keys=False)
    if path.exists() and StudyConfig.from_text(path.read_text(encoding='utf-8')) != cfg:
        raise StudyError(f'{path} holds another study file: this directory was simulated with other settings; '
                         'use another --out')
    write_text_atomic(path, text)
    return cfg, path


def graph_params(cfg: StudyConfig, args: SimulateArgs, study_path: Path, out: Path, port: int) -> dict[str, dict]:
    """Parameters of every node of the study graph."""
    view_hz = min(120.0, 25.0 * args.real_time_factor + 10.0)
    models = {'encoder_node': cfg.encoder_model, 'policy_node': cfg.policy_model}
    nodes = {
        'sim_node': {'seed': int(args.seed), 'real_time_factor': float(args.real_time_factor), 'auto_reset': False,
                     'scene_seed': int(cfg.scene_seed), 'camera_rate_hz': 20.0,
                     'episode_timeout_s': float(args.max_landing_s)},
        'encoder_node': {'use_sim_time': True},
        'policy_node': {'use_sim_time': True, 'mode': cfg.assistant_mode, 'assist_enabled': False},
        'pilot_station': {'use_sim_time': True, 'port': int(port), 'study_config': str(study_path.resolve()),
                          'study_dir': str(out.resolve()), 'view_rate_hz': view_hz, 'camera_rate_hz': 0.0,
                          'mode': 'study'},
    }
    for node, model in models.items():
        if model:
            nodes[node]['model_path'] = str(Path(model).expanduser().resolve())
    return nodes


class StudyGraph:
    """The study's node graph as child processes (assist_lab.graph_eval.NodeGroup) on one domain."""

    def __init__(self, params: dict[str, dict], domain_id: int, log_dir: Path):
        from assist_lab.graph_eval import NodeGroup
        self.params = params
        self.group = NodeGroup(domain_id, log_dir)
        self.url = f"http://127.0.0.1:{params['pilot_station']['port']}/"

    def start(self) -> None:
        """Start every node; returns once the station's page answers."""
        for name in ('encoder_node', 'policy_node', 'sim_node'):
            if name == 'encoder_node' and self.params['policy_node']['mode'] != 'latent':
                continue
            self.group.start(name, self.params[name])
        self.start_station()

    def start_station(self) -> None:
        """(Re)start pilot_station and wait for its page."""
        import urllib.request
        self.group.start('pilot_station', self.params['pilot_station'])
        end = time.monotonic() + STATION_STARTUP_S
        while True:
            self.group.check()
            try:
                with urllib.request.urlopen(self.url, timeout=2.0) as resp:
                    if resp.status == 200:
                        return
            except OSError:
                pass
            if time.monotonic() > end:
                raise RuntimeError(f'pilot_station not serving {self.url} after {STATION_STARTUP_S:.0f} s:\n'
                                   f'{self.group.tail("pilot_station")}')
            time.sleep(0.3)

    def kill_station(self) -> None:
        """SIGKILL the station (a crash: nothing is closed cleanly)."""
        import os
        proc = self.group.procs['pilot_station']
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(10)

    def stop(self) -> None:
        """Stop every node."""
        self.group.stop()


def participant_done(out: Path, pid: str) -> bool:
    """Whether `pid`'s directory holds a finished protocol."""
    path = out / pid / 'survey.json'
    try:
        return json.loads(path.read_text(encoding='utf-8')).get('survey') is not None
    except (OSError, ValueError, AttributeError):
        return False


def run_browser_participant(url: str, profile: Profile, rtf: float, work: Path, on_landing=None) -> dict:
    """One participant through the station page in headless Chromium (see browser_participant)."""
    from .browser_participant import BrowserParticipant
    return BrowserParticipant(url, profile, rtf, work, on_landing=on_landing).run()


def simulate(args: SimulateArgs) -> list[dict]:
    """Run the simulated study; returns one summary per participant."""
    ids = participant_ids(args)                 # before anything is written: no directory outside --out
    out = Path(args.out)
    sim_dir = out / '.simulation'
    sim_dir.mkdir(parents=True, exist_ok=True)
    cfg, study_path = study_file(args, sim_dir)
    from assist_lab.graph_eval import pick_domain_id
    domain = args.domain_id or pick_domain_id()
    params = graph_params(cfg, args, study_path, out, free_tcp_port())
    profiles = draw_profiles(args.participants, args.seed, tuple(args.families), args.practice, args.id_prefix,
                             cue_trust=tuple(args.cue_trust))
    if [p.pid for p in profiles] != ids:
        raise StudyError(f'drawn participant IDs {[p.pid for p in profiles]} are not {ids}')
    if args.only:
        profiles = [p for p in profiles if p.pid in args.only]
    graph = StudyGraph(params, domain, sim_dir / ('logs' if not args.only else f'logs_{"_".join(args.only)}'))
    results = []
    t0 = time.monotonic()
    per_participant = cfg.n_blocks * cfg.landings_per_block + cfg.practice_landings   # at most (practice may end early)
    bar = tqdm(total=len(profiles) * per_participant, desc='simulated study', unit='landing', file=sys.stderr,
               mininterval=1.0, dynamic_ncols=False, disable=None)
    try:
        graph.start()
        log.info('study graph up on domain %d, station %s', domain, graph.url)
        for i, prof in enumerate(profiles):
            if participant_done(out, prof.pid):
                log.info('%s: done already, skipped', prof.pid)
                bar.total -= per_participant
                continue
            (out / prof.pid).mkdir(parents=True, exist_ok=True)
            write_text_atomic(out / prof.pid / 'simulated_participant.json',
                         json.dumps(dataclasses.asdict(prof), indent=1) + '\n')
            t = time.monotonic()
            if i < args.browser_participants:
                res = run_browser_participant(graph.url, prof, args.real_time_factor, sim_dir / f'browser_{prof.pid}',
                                              on_landing=lambda: bar.update(1))
            else:
                res = asyncio.run(Participant(graph.url, prof, args.real_time_factor,
                                              on_landing=lambda: bar.update(1)).run())
            bar.total -= per_participant - res['landings_flown']           # practice ended early: fewer to fly
            bar.refresh()
            res['wall_s'] = round(time.monotonic() - t, 1)
            res['browser'] = i < args.browser_participants
            results.append(res)
            log.info('%s (%s, beta %.2f%s): %d landings in %.0f s', prof.pid, prof.family, prof.beta,
                     ', browser' if res['browser'] else '', res['landings_flown'], res['wall_s'])
    finally:
        bar.close()
        graph.stop()
    summary = {'participants': results, 'wall_s': round(time.monotonic() - t0, 1), 'domain_id': domain,
               'settings': dataclasses.asdict(args)}
    path = sim_dir / ('summary.json' if not args.only else f'summary_{"_".join(args.only)}.json')
    write_text_atomic(path, json.dumps(summary, indent=1, default=list) + '\n')
    return results


def main(argv: list[str] | None = None) -> int:
    """Console entry point."""
    cmd = parse_command(SimulateArgs, 'simulate_study', __doc__, HELP, argv)
    parser, args = cmd.parser, cmd.settings
    from assist_sim.pilots import GRAPH_PILOT_NAMES as PILOT_NAMES
    bad = [f for f in args.families if f not in PILOT_NAMES]
    if bad:
        parser.error(f'--families: unknown pilot {", ".join(bad)} (choose from {", ".join(PILOT_NAMES)})')
    if args.browser_participants > args.participants:
        parser.error('--browser-participants must be at most --participants')
    drawn = set(participant_ids(args))
    unknown = sorted(set(args.only) - drawn)
    if unknown:
        parser.error(f'--only: {", ".join(unknown)} not among the {args.participants} participants '
                     f'({args.id_prefix}01-{args.id_prefix}{args.participants:02d})')
    signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with logging_redirect_tqdm():
            results = simulate(args)
    except KeyboardInterrupt:
        print(f'interrupted: the graph was stopped; what was recorded is in {args.out} (re-run to go on)',
              file=sys.stderr)
        return 130
    except (OSError, StudyError, RuntimeError) as exc:
        print(f'error: {exc}', file=sys.stderr)
        return 1
    print(f'{len(results)} simulated participants in {args.out}; analyse with: analyze_study {args.out}/* '
          f'--out {args.out.rstrip("/")}_analysis')
    return 0


if __name__ == '__main__':
    sys.exit(main())
