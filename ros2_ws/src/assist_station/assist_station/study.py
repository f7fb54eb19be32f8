"""The paper's user study as data and a protocol: configuration, questionnaires, per-participant files. No rclpy.

A study is one YAML file (``StudyConfig``; the shipped example is ``config/study.yaml``): the scene, the
predefined landing sequence of a block (the same goal pads for every participant), the practice landings
(the paper allowed up to 14, goal drawn at random, feedback after each), the conditions (``conditions``:
the paper's ``unassisted`` and ``assisted``, and optionally ``assisted_cues``: assisted, with the pilot
station's three intent cues shown), the assistant that flies the assisted blocks and the texts the page
shows. A participant goes through

    consent -> practice -> block 1 -> SUS -> block 2 -> SUS [-> block 3 -> SUS] -> concluding survey -> done

one block per condition, in the order that follows from the participant ID (``condition_order``: a row
of a balanced Latin square picked by the ID's trailing number; with the two conditions an odd number
starts unassisted, an even one assisted). Everything a participant produces lives in one directory
(``ParticipantStore``): the study file as run (``study.yaml``), ``landings.csv`` (one fsynced row per
finished landing, with its measures: time to land, path length, key presses and corrective ones),
``survey.json`` (SUS answers per block with its condition, and the concluding survey's 21 answers,
written atomically), ``protocol.log`` (one JSON line per protocol event) and ``bags/`` (a rosbag2 bag per
landing, written by the station). The protocol's position is derived from those files only, so a
station restarted mid-block resumes at the next unfinished landing: rows already written are never
rewritten or repeated, and a landing that was in flight is flown again (its partial bag stays, the new
one gets its own name).
"""
from __future__ import annotations

import csv
import errno
import hashlib
import io
import json
import logging
import os
import re
import threading
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from assist_bridge.teleop_core import KEY_BINDINGS
from assist_common.atomic import write_text_atomic
from assist_common.settings import check_named, setting

from .station_core import BROWSER_KEYS, STOP_KEY

CONDITIONS = ('unassisted', 'assisted')                  # the paper's two (Table I compares them)
CUE_CONDITION = 'assisted_cues'                           # assisted, with the station's intent cues shown
ALL_CONDITIONS = (*CONDITIONS, CUE_CONDITION)             # every condition a study file may list, in this order
ASSISTED_CONDITIONS = ('assisted', CUE_CONDITION)         # the assistant flies along (policy_node assist_enabled)
PHASES = ('consent', 'practice', 'block1', 'sus1', 'block2', 'sus2', 'survey', 'done')     # the two-block study's
PRACTICE_BLOCK = 0
PARTICIPANT_ID = re.compile(r'[A-Za-z0-9][A-Za-z0-9_-]{0,31}')        # the whole ID (fullmatch: no trailing newline)
MAX_CONFIG_BYTES = 256 * 1024
MAX_TEXT_CHARS = 20_000            # a study file's page texts (intro, consent, thanks)
EVENT_START = '{"t": "'         # how every protocol.log line begins (json.dumps of an entry whose first key is t)
_LOG = logging.getLogger('assist_station.study')

# The System Usability Scale (Brooke 1996), item order fixed: odd items positive, even items negative.
SUS_ITEMS = (
    'I think that I would like to use this system frequently.',
    'I found the system unnecessarily complex.',
    'I thought the system was easy to use.',
    'I think that I would need the support of a technical person to be able to use this system.',
    'I found the various functions in this system were well integrated.',
    'I thought there was too much inconsistency in this system.',
    'I would imagine that most people would learn to use this system very quickly.',
    'I found the system very cumbersome to use.',
    'I felt very confident using the system.',
    'I needed to learn a lot of things before I could get going with this system.',
)

# The paper's concluding survey (its Tables II-III). kind: choice (one option; answer = its number 1..n),
# multi (tick all that apply; answer = sorted option numbers), likert (1 = strongly disagree .. 5 = strongly agree).
SURVEY = (
    {'id': 1, 'kind': 'choice', 'text': 'Have you had any experience with flying a physical drone?',
     'options': ['Yes', 'No']},
    {'id': 2, 'kind': 'choice', 'text': 'How many hours of experience have you with flying physical drones?',
     'options': ['0-5', '5-10', '10-20', '20-50', '50+']},
    {'id': 3, 'kind': 'choice', 'text': 'How confident are you with flying physical drones?',
     'options': ['1', '2', '3', '4', '5']},
    {'id': 4, 'kind': 'multi', 'text': 'For what purpose have you flown a physical drone? (Tick all that apply)',
     'options': ['Recreational', 'Inspection', 'Other']},
    {'id': 5, 'kind': 'choice', 'text': 'How often do you play video games? (e.g. PC/PS4/Xbox)',
     'options': ['Never', 'Monthly', 'Weekly', 'Regularly', 'Daily']},
    {'id': 6, 'kind': 'choice', 'text': 'How many hours have you spent on games involving flying?',
     'options': ['0-10', '10-25', '25-100', '100-200', '200+']},
    {'id': 7, 'kind': 'multi', 'text': 'When you play video games, what input device do you use? (Tick all that '
                                       'apply)', 'options': ['Keyboard', 'Mouse', 'Controller', 'Touch screen',
                                                             'Other']},
    *({'id': i, 'kind': 'likert', 'text': text} for i, text in enumerate((
        'I felt confident in landing unassisted',
        'I felt confident in landing assisted',
        'I felt stressed when landing unassisted',
        'I felt stressed when landing assisted',
        'I felt the task was difficult to perform unassisted',
        'I felt the task was difficult to perform assisted',
        'I was able to land with greater accuracy whilst being assisted',
        'I was able to land quicker whilst being assisted',
        'I trust the actions of the assistant',
        "The assistant didn't do what I wanted to do",
        'I had to fight the assistant for control',
        'I prefer to use the assistant when landing',
        'I felt being unassisted gave me more freedom',
        'I believe that if I practiced, I could perform better without assistance than with assistance',
    ), start=8)),
)
EXPERIENCE_QUESTIONS = (2, 3, 5, 6)     # the paper's "experienced" rating and its Fig. 8 experience level

BASE_COLUMNS = ('participant', 'block', 'condition', 'order', 'trial', 'goal_index', 'landed_index',
                'nearest_index', 'error_m', 'nearest_error_m', 'success', 'crash', 'outcome', 'duration_s',
                'started_on_pad', 'start_pad', 'assist_live', 'episode', 'bag', 'recorded_utc')
# per-landing measures, after the base columns (a file written without them is still read; empty: not measured):
# path flown (m, /odom during the landing), key presses and the corrective ones among them (KeyCounter)
MEASURE_COLUMNS = ('path_length_m', 'key_presses', 'corrective_keys')
LANDING_COLUMNS = BASE_COLUMNS + MEASURE_COLUMNS


class StudyError(ValueError):
    """A study file, participant ID, answer or protocol step that cannot be used; the text says why."""


# ----------------------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class StudyConfig:
    """One study: scene, landing sequence, practice, assistant and the page's texts (a YAML file's keys)."""

    name: str = setting('assisted-landing-study', nonempty=True)
    scene_seed: int = setting(7, ge=0, lt=2 ** 31)   # every landing flies the scene of this sim seed
    # goal pads of a block, in order (each < n_pads)
    sequence: tuple[int, ...] = setting((2, 0, 4, 1, 3, 0, 2, 4, 3, 1, 4, 2, 0, 3, 1, 2), ge=0, min_len=1,
                                        max_len=200)
    n_pads: int = setting(5, ge=1, le=64)            # pads in the scene (the sim's scene.n_pads)
    practice_landings: int = setting(14, ge=0, le=100)   # at most this many practice landings (may stop early)
    practice_seed: int = setting(0, ge=0)            # practice goals: drawn from this seed and the participant ID
    practice_condition: str = 'first'                 # first (the participant's first block's) or one of conditions
    # one block each; the paper's two, or also assisted_cues (each once)
    conditions: tuple[str, ...] = setting(CONDITIONS, choices=ALL_CONDITIONS)
    assistant_mode: str = setting('latent', choices=('latent', 'oracle', 'end_to_end'))  # checked at start
    policy_model: str = ''                    # the TD3 actor policy_node must fly ('' = the shipped one; checked)
    encoder_model: str = ''                   # the CM-VAE encoder_node must use (latent; '' = the shipped one; checked)
    record_bags: bool = True                  # a rosbag2 bag per landing under <participant>/bags/
    bag_topics: tuple[str, ...] = ()          # empty: the contract's default set (names start with /)
    # wall seconds without a landing result: the landing is flown again
    landing_timeout_s: float = setting(120.0, ge=5.0, le=3600.0)
    intro_text: str = setting('Land the drone on the platform marked in green. W/A/S/D move it forward, left, back '
                              'and right; the up and down arrows climb and descend; Space stops it.',
                              max_chars=MAX_TEXT_CHARS)
    consent_text: str = setting('Your landings, the answers you give and the flight recordings are stored under your '
                                'participant ID only. You may stop at any time.', max_chars=MAX_TEXT_CHARS)
    thanks_text: str = setting('Thank you for taking part. You may close this page.', max_chars=MAX_TEXT_CHARS)

    def __post_init__(self) -> None:
        """StudyError (one line) for a value outside its field's type or range, or fields that disagree."""
        try:
            check_named(self)
        except ValueError as exc:
            raise StudyError(f'study file: {exc}') from None
        # one order however the file lists them (the blocks' order is the participant ID's)
        object.__setattr__(self, 'conditions', tuple(c for c in ALL_CONDITIONS if c in self.conditions))

    def check_relations(self) -> None:
        """The rules between fields (check_named runs it after the fields' own)."""
        if any(g >= self.n_pads for g in self.sequence):
            raise ValueError(f'sequence must list pad indices in 0..n_pads-1 ({self.n_pads - 1}), got '
                             f'{list(self.sequence)}')
        if len(set(self.conditions)) != len(self.conditions) or not set(CONDITIONS) <= set(self.conditions):
            raise ValueError(f'conditions must list {", ".join(CONDITIONS)} and optionally {CUE_CONDITION}, each '
                             f'once, got {list(self.conditions)}')
        if self.practice_condition not in ('first', *self.conditions):
            raise ValueError(f'practice_condition must be first or one of the conditions '
                             f'({", ".join(self.conditions)}), got {self.practice_condition!r}')
        if not all(t.startswith('/') for t in self.bag_topics):
            raise ValueError(f'bag_topics must list topic names starting with /, got {list(self.bag_topics)}')

    @property
    def landings_per_block(self) -> int:
        """Landings in each block (the sequence's length; the paper: 16)."""
        return len(self.sequence)

    @property
    def n_blocks(self) -> int:
        """Blocks of the study: one per condition (the paper: 2)."""
        return len(self.conditions)

    @classmethod
    def from_text(cls, text: str, source: str = 'study file') -> StudyConfig:
        """Parse a study YAML document (unknown keys and wrong types refused); StudyError says why."""
        if len(text.encode('utf-8')) > MAX_CONFIG_BYTES:
            raise StudyError(f'{source}: larger than {MAX_CONFIG_BYTES // 1024} kB')
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as exc:
            raise StudyError(f'{source}: not valid YAML: {str(exc).splitlines()[0]}') from None
        if data is None:
            data = {}
        if not isinstance(data, dict):
            raise StudyError(f'{source}: expected a mapping of study settings, got {type(data).__name__}')
        known = {f.name for f in fields(cls)}
        unknown = sorted(str(k) for k in data if k not in known)
        if unknown:
            raise StudyError(f'{source}: unknown setting(s) {", ".join(unknown)} (known: {", ".join(sorted(known))})')
        values = dict(data)
        for key in ('sequence', 'bag_topics', 'conditions'):
            if key in values:
                if not isinstance(values[key], list):
                    raise StudyError(f'{source}: {key} must be a list')
                values[key] = tuple(values[key])
        try:
            return cls(**values)
        except StudyError as exc:
            raise StudyError(f'{source}: {str(exc).removeprefix("study file: ")}') from None

    @classmethod
    def load(cls, path: str | Path) -> tuple[StudyConfig, str]:
        """(config, the file's text) of a study YAML file; StudyError (one line) when unusable."""
        path = Path(path)
        try:
            if not path.is_file():
                raise StudyError(f'study file {path}: not a regular file')
            if path.stat().st_size > MAX_CONFIG_BYTES:
                raise StudyError(f'study file {path}: larger than {MAX_CONFIG_BYTES // 1024} kB')
            text = path.read_text(encoding='utf-8')
        except (OSError, UnicodeDecodeError) as exc:
            raise StudyError(f'study file {path}: cannot read: {exc}') from None
        return cls.from_text(text, f'study file {path}'), text

    def to_dict(self) -> dict[str, Any]:
        """The settings as plain YAML/JSON values (``conditions`` only when it is not the paper's two)."""
        d = asdict(self)
        d['sequence'], d['bag_topics'] = list(self.sequence), list(self.bag_topics)
        if self.conditions == CONDITIONS:
            del d['conditions']
        else:
            d['conditions'] = list(self.conditions)
        return d


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


# ----------------------------------------------------------------------------------------- protocol rules
def check_participant_id(pid: Any) -> str:
    """A usable participant ID (1-32 of A-Z a-z 0-9 _ -, starting alphanumeric) or StudyError."""
    if not isinstance(pid, str) or not PARTICIPANT_ID.fullmatch(pid):
        raise StudyError('participant ID: 1-32 letters, digits, _ or -, starting with a letter or digit')
    return pid


def latin_square(conditions: tuple[str, ...]) -> tuple[tuple[str, ...], ...]:
    """The rows (block orders) of a balanced Latin square over `conditions` (Williams design): each condition
    in each block equally often and each one right after each other equally often. First row 0, 1, n-1, 2,
    n-2, ...; row i adds i to it (mod n); with an odd n the mirrored rows follow (2n rows). Two conditions:
    (a, b), (b, a); three: all six orders."""
    n = len(conditions)
    first, low, high = [0], 1, n - 1
    while len(first) < n:
        first.append(low if len(first) % 2 else high)
        low, high = (low + 1, high) if len(first) % 2 == 0 else (low, high - 1)
    rows = [tuple(conditions[(k + i) % n] for k in first) for i in range(n)]
    if n % 2:
        rows += [row[::-1] for row in rows]
    return tuple(rows)


def participant_number(pid: str) -> int:
    """The number that picks a participant's block order: the ID's trailing number, else its SHA-256's first byte."""
    m = re.search(r'(\d+)\Z', pid)
    return int(m.group(1)) if m else hashlib.sha256(pid.encode()).digest()[0]


def condition_order(pid: str, conditions: tuple[str, ...] = CONDITIONS) -> tuple[str, ...]:
    """The conditions of blocks 1, 2, ... for participant `pid` (counterbalanced): row (number - 1) mod rows of
    the balanced Latin square over `conditions`. Two conditions: an odd number starts unassisted, an even one
    assisted."""
    rows = latin_square(tuple(conditions))
    return rows[(participant_number(pid) - 1) % len(rows)]


def first_condition(pid: str, conditions: tuple[str, ...] = CONDITIONS) -> str:
    """The condition of block 1 (counterbalanced, ``condition_order``)."""
    return condition_order(pid, conditions)[0]


def block_condition(pid: str, block: int, conditions: tuple[str, ...] = CONDITIONS) -> str:
    """Condition of block `block` (1..number of conditions) for participant `pid`; StudyError for another block."""
    order = condition_order(pid, conditions)
    if not (_is_int(block) and 1 <= block <= len(order)):
        raise StudyError(f'block {block!r}: the study has blocks 1-{len(order)}')
    return order[block - 1]


def order_name(pid: str, conditions: tuple[str, ...] = CONDITIONS) -> str:
    """The participant's block order as written in landings.csv: 'unassisted_first' or 'assisted_first' with the
    paper's two conditions, else the conditions joined by '-' (e.g. 'assisted-assisted_cues-unassisted')."""
    order = condition_order(pid, conditions)
    return f'{order[0]}_first' if len(order) == 2 else '-'.join(order)


def phases(n_blocks: int) -> tuple[str, ...]:
    """The protocol's phases for a study of `n_blocks` blocks (two: PHASES)."""
    blocks = tuple(p for b in range(1, n_blocks + 1) for p in (f'block{b}', f'sus{b}'))
    return ('consent', 'practice', *blocks, 'survey', 'done')


def phase_block(phase: str) -> int | None:
    """The block a 'block<k>' or 'sus<k>' phase belongs to (None for the others)."""
    m = re.fullmatch(r'(?:block|sus)([1-9][0-9]*)', phase)
    return int(m.group(1)) if m else None


def practice_goals(cfg: StudyConfig, pid: str) -> list[int]:
    """The practice landings' goal pads for `pid` (random, reproducible from practice_seed and the ID)."""
    salt = int.from_bytes(hashlib.sha256(pid.encode()).digest()[:4], 'little')
    rng = np.random.default_rng([cfg.practice_seed, salt])
    return [int(g) for g in rng.integers(cfg.n_pads, size=cfg.practice_landings)]


def sus_score(answers: list[int]) -> float:
    """SUS score 0-100 of ten 1-5 answers (odd items: answer - 1, even items: 5 - answer; sum x 2.5)."""
    a = check_sus(answers)
    return 2.5 * sum((x - 1) if i % 2 == 0 else (5 - x) for i, x in enumerate(a))


def check_sus(answers: Any) -> list[int]:
    """Ten integer answers in 1..5, or StudyError."""
    if not (isinstance(answers, list) and len(answers) == len(SUS_ITEMS)
            and all(_is_int(x) and 1 <= x <= 5 for x in answers)):
        raise StudyError(f'SUS: expected {len(SUS_ITEMS)} answers, each an integer 1-5')
    return list(answers)


def check_survey(answers: Any) -> dict[str, Any]:
    """The concluding survey's 21 answers keyed '1'..'21' (choice/likert: 1..n, multi: sorted distinct option
    numbers, possibly none), or StudyError naming the first bad one."""
    if not isinstance(answers, dict):
        raise StudyError('survey: expected an object of answers keyed by question number')
    out: dict[str, Any] = {}
    extra = set(map(str, answers)) - {str(q['id']) for q in SURVEY}
    if extra:
        raise StudyError(f'survey: unknown question(s) {", ".join(sorted(extra))}')
    for q in SURVEY:
        key = str(q['id'])
        if key not in answers:
            raise StudyError(f'survey: question {key} is not answered')
        v = answers[key]
        n = len(q.get('options', ())) or 5
        if q['kind'] == 'multi':
            if not (isinstance(v, list) and all(_is_int(x) and 1 <= x <= n for x in v) and len(set(v)) == len(v)):
                raise StudyError(f'survey: question {key} takes a list of distinct option numbers 1-{n}')
            out[key] = sorted(v)
        else:
            if not (_is_int(v) and 1 <= v <= n):
                raise StudyError(f'survey: question {key} takes one answer 1-{n}')
            out[key] = v
    return out


@dataclass(frozen=True)
class LandingSpec:
    """What the next landing flies: its block (0 = practice), condition, trial number and goal pad."""

    block: int
    condition: str
    trial: int
    goal_index: int

    @property
    def assisted(self) -> bool:
        """Whether the assistant flies along (assisted, assisted_cues)."""
        return self.condition in ASSISTED_CONDITIONS

    @property
    def cues(self) -> bool:
        """Whether the station shows the assistant's intent cues (assisted_cues only)."""
        return self.condition == CUE_CONDITION

    @property
    def name(self) -> str:
        """Short name (bag names, logs): practice_03, block1_12."""
        return f"{'practice' if self.block == PRACTICE_BLOCK else f'block{self.block}'}_{self.trial:02d}"


# ----------------------------------------------------------------------------------------- measures
# the horizontal keys: browser key code -> (axis 0 forward / 1 left, direction +1 / -1), the station's bindings
HORIZONTAL_KEYS = {code: KEY_BINDINGS[token] for code, token in BROWSER_KEYS.items() if KEY_BINDINGS[token][0] < 2}


class KeyCounter:
    """The pilot's key presses during one landing and the corrective ones among them (thread-safe).

    ``note(held)`` gets every change of the pilot's held keys as the station's key state has them (press
    order; a key the page stopped refreshing counts as released). A key press is a key-down event: a key
    (W/A/S/D, the arrows, Space) in the held set that was not in the one before. A press is corrective when
    it is the stop key (Space), or a horizontal key whose direction is opposite to the last horizontal key held
    on its axis during the landing (W against S on the forward axis, A against D on the left axis; a key held
    when the landing starts counts as held): the pilot takes back what it asked for on that axis. Vertical keys
    are presses, never corrective. Presses are counted between ``start()`` and ``stop()``.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._held: tuple[str, ...] = ()
        self._counting = False
        self._last: dict[int, int] = {}       # axis -> direction of the last horizontal key held on it
        self.presses = 0
        self.corrective = 0

    def note(self, held: tuple[str, ...] | list[str]) -> None:
        """The pilot's held keys now (in press order)."""
        held = tuple(held)
        with self._lock:
            pressed = [k for k in held if k not in self._held]
            self._held = held
            if not self._counting:
                return
            for key in pressed:
                self.presses += 1
                if key == STOP_KEY:
                    self.corrective += 1
                elif key in HORIZONTAL_KEYS:
                    axis, direction = HORIZONTAL_KEYS[key]
                    if self._last.get(axis) == -direction:
                        self.corrective += 1
                    self._last[axis] = direction

    def start(self) -> None:
        """A landing starts: counts from zero; the horizontal keys held now are the last ones on their axes."""
        with self._lock:
            self._counting = True
            self.presses = self.corrective = 0
            self._last = {}
            for key in self._held:
                if key in HORIZONTAL_KEYS:
                    axis, direction = HORIZONTAL_KEYS[key]
                    self._last[axis] = direction

    def stop(self) -> tuple[int, int] | None:
        """The landing ended: (key presses, corrective presses) since start(); None when it was not started."""
        with self._lock:
            if not self._counting:
                return None
            self._counting = False
            return self.presses, self.corrective


# ----------------------------------------------------------------------------------------- files
def _csv_value(v: Any) -> str:
    if v is None:
        return ''
    if isinstance(v, bool):
        return 'true' if v else 'false'
    if isinstance(v, float):
        return f'{v:.4f}'
    return str(v)


def _split_log_line(line: str) -> tuple[dict[str, Any] | None, str]:
    """(the event a protocol.log line holds, or None; the bytes before it that are no event).

    A write cut short (crash, full disk) leaves a fragment without its newline; an event appended after it
    by a version that did not start a fresh line shares its line: that event is kept, the fragment skipped.
    """
    try:
        return json.loads(line), ''
    except ValueError:
        pass
    start = line.find(EVENT_START, 1)
    while start != -1:
        try:
            return json.loads(line[start:]), line[:start]
        except ValueError:
            start = line.find(EVENT_START, start + 1)
    return None, line


class ParticipantStore:
    """One participant's directory: study file, landings.csv, survey.json, protocol.log, bags/.

    The store reads and writes only inside the study directory: a participant directory, file or bags/
    that is a symbolic link is refused (StudyError), and files are opened without following links.
    """

    def __init__(self, root: str | Path, pid: str, cfg: StudyConfig, config_text: str):
        self.pid = check_participant_id(pid)
        self.cfg = cfg
        self.root = Path(root)
        self.dir = self.root / pid
        self.bags = self.dir / 'bags'
        self.landings_path = self.dir / 'landings.csv'
        self.survey_path = self.dir / 'survey.json'
        self.log_path = self.dir / 'protocol.log'
        self.created = not os.path.lexists(self.dir)      # this store made the directory (discard() may remove it)
        self.columns = LANDING_COLUMNS     # an existing landings.csv's own: one written without the measures stays so
        try:
            self._open(config_text)
        except BaseException:
            if self.created:
                self.discard()
            raise

    def _open(self, config_text: str) -> None:
        self._check_dir()
        self.dir.mkdir(parents=True, exist_ok=True)
        copy = self._plain(self.dir / 'study.yaml')
        if copy.exists():
            try:
                previous = StudyConfig.from_text(self._read(copy).decode('utf-8'), str(copy))
            except (OSError, UnicodeDecodeError) as exc:
                raise StudyError(f'{copy}: cannot read: {exc}') from None
            if previous != self.cfg:
                raise StudyError(f'participant {self.pid} was run with a different study file ({copy}); use another '
                                 'participant ID or study directory')
        else:
            write_text_atomic(copy, config_text)
        self.events = self._load_events()
        self.rows = self._load_rows()
        self.survey = self._load_survey()

    def discard(self) -> None:
        """Remove the directory this store created (nothing else was in it: a begin that was not accepted)."""
        for name in ('study.yaml', 'protocol.log'):
            path = self.dir / name
            if path.is_file() and not path.is_symlink():
                path.unlink()
        try:
            self.dir.rmdir()
        except FileNotFoundError:
            pass
        except OSError as exc:
            _LOG.warning('%s: left in place (%s)', self.dir, exc.strerror or exc)

    # ---------------------------------------------------------------- paths
    def _check_dir(self) -> None:
        if self.dir.is_symlink():
            raise StudyError(f'{self.dir}: participant directory is a symbolic link; the study store reads and '
                             f'writes only inside {self.root}')
        if os.path.lexists(self.dir) and not self.dir.is_dir():
            raise StudyError(f'{self.dir}: not a directory')

    def _plain(self, path: Path) -> Path:
        """`path` (in this participant's directory) if neither it nor the directory is a symbolic link."""
        self._check_dir()
        if path.is_symlink():
            raise StudyError(f'{path}: a symbolic link; the study store reads and writes only plain files inside '
                             f'{self.root}')
        return path

    def _fd(self, path: Path, flags: int) -> int:
        """os.open without following a link (a link put there since the check is refused too)."""
        try:
            return os.open(self._plain(path), flags | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise StudyError(f'{path}: a symbolic link; the study store reads and writes only plain files '
                                 f'inside {self.root}') from None
            raise

    def _read(self, path: Path) -> bytes:
        with os.fdopen(self._fd(path, os.O_RDONLY), 'rb') as fh:
            return fh.read()

    def _cut(self, path: Path, size: int) -> None:
        """Truncate `path` to `size` bytes (a torn last line), fsynced."""
        fd = self._fd(path, os.O_WRONLY)
        try:
            os.ftruncate(fd, size)
            os.fsync(fd)
        finally:
            os.close(fd)

    def _append(self, path: Path, data: bytes) -> None:
        """Append `data` (whole lines) fsynced, on a fresh line; a failed write is taken back (file as before)."""
        fd = self._fd(path, os.O_RDWR | os.O_APPEND | os.O_CREAT)
        try:
            size = os.fstat(fd).st_size
            if size and os.pread(fd, 1, size - 1) != b'\n':
                data = b'\n' + data          # the last line was cut short: it must not swallow this one
            try:
                view = memoryview(data)
                while view:
                    view = view[os.write(fd, view):]
                os.fsync(fd)
            except OSError:
                try:                         # a full disk: take the partial line back, the file stays whole
                    os.ftruncate(fd, size)
                except OSError as exc:
                    _LOG.warning('%s: a partial line could not be taken back (%s); it is skipped when read',
                                 path, exc.strerror or exc)
                raise
        finally:
            os.close(fd)

    # ---------------------------------------------------------------- reading
    def _load_rows(self) -> list[dict[str, str]]:
        path = self._plain(self.landings_path)
        if not path.exists():
            return []
        raw = self._read(path)
        if raw and not raw.endswith(b'\n'):        # a row cut by a crash mid-write was never recorded: drop it
            cut = raw.rfind(b'\n') + 1
            self._cut(path, cut)
            self.log('torn_row_dropped', bytes=len(raw) - cut)
            raw = raw[:cut]
        reader = csv.DictReader(io.StringIO(raw.decode('utf-8')))
        if reader.fieldnames is not None:
            if tuple(reader.fieldnames) not in (LANDING_COLUMNS, BASE_COLUMNS):
                raise StudyError(f'{path}: columns differ from this station\'s; not appending to it')
            self.columns = tuple(reader.fieldnames)
            if self.columns == BASE_COLUMNS:
                _LOG.warning('%s: written without the measure columns (%s); its rows go on without them', path,
                             ', '.join(MEASURE_COLUMNS))
        rows = []
        for row in reader:
            if None in row or None in row.values():     # a row an interrupted write cut short: never recorded
                _LOG.warning('%s line %d: skipped a landing row cut short by an interrupted write', path,
                             reader.line_num)
                continue
            rows.append(row)
        return rows

    def _load_survey(self) -> dict[str, Any]:
        path = self._plain(self.survey_path)
        if not path.exists():
            return {'participant': self.pid, 'sus': {}, 'survey': None}
        try:
            data = json.loads(self._read(path).decode('utf-8'))
        except (OSError, ValueError) as exc:
            raise StudyError(f'{path}: unreadable ({exc}); not overwriting it') from None
        if not isinstance(data, dict) or not isinstance(data.get('sus'), dict):
            raise StudyError(f'{path}: not a survey file; not overwriting it')
        return data

    def _load_events(self) -> list[dict[str, Any]]:
        path = self._plain(self.log_path)
        if not path.exists():
            return []
        raw = self._read(path)
        torn = 0
        if raw and not raw.endswith(b'\n'):        # an event cut by a crash mid-write did not complete: drop it
            cut = raw.rfind(b'\n') + 1
            torn = len(raw) - cut
            self._cut(path, cut)
            raw = raw[:cut]
            _LOG.warning('%s: dropped %d bytes of a last line cut short by an interrupted write', path, torn)
        events = []
        for n, line in enumerate(raw.decode('utf-8', errors='replace').splitlines(), 1):
            e, fragment = _split_log_line(line)
            if fragment.strip():
                _LOG.warning('%s line %d: skipped %d bytes of an event cut short by an interrupted write', path, n,
                             len(fragment.encode('utf-8')))
            if isinstance(e, dict) and isinstance(e.get('event'), str):
                events.append(e)
        self.events = events
        if torn:
            self.log('torn_event_dropped', bytes=torn)
        return events

    # ---------------------------------------------------------------- writing
    def log(self, event: str, **data: Any) -> None:
        """Append one protocol event (fsynced JSON line); a failed write leaves the file as it was."""
        entry = {'t': time.strftime('%Y-%m-%dT%H:%M:%S', time.gmtime()) + f'.{int(time.time() * 1000) % 1000:03d}Z',
                 'event': event, **data}
        self._append(self.log_path, (json.dumps(entry, default=str) + '\n').encode('utf-8'))
        if hasattr(self, 'events'):
            self.events.append(entry)

    def append_row(self, row: dict[str, Any]) -> dict[str, str]:
        """Append one landing row (header first on a new file), fsynced; returns it as stored. A file written
        without the measure columns gets its rows without them (the file stays one table)."""
        path = self._plain(self.landings_path)
        new = not path.exists() or path.stat().st_size == 0
        columns = LANDING_COLUMNS if new else self.columns
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=columns, lineterminator='\n')
        if new:
            writer.writeheader()
        stored = {k: _csv_value(row.get(k)) for k in columns}
        writer.writerow(stored)
        self._append(path, buf.getvalue().encode('utf-8'))
        self.columns = columns
        self.rows.append(stored)
        return stored

    def save_survey(self, survey: dict[str, Any]) -> None:
        """Write `survey` to survey.json atomically, then hold it (a failed write changes nothing)."""
        write_text_atomic(self._plain(self.survey_path), json.dumps(survey, indent=1) + '\n')
        self.survey = survey

    def new_bag_path(self, name: str) -> Path:
        """A bag directory name under bags/ that does not exist yet (a repeated landing gets _2, _3, ...)."""
        self._plain(self.bags).mkdir(exist_ok=True)
        path, k = self.bags / name, 1
        while os.path.lexists(path):
            k += 1
            path = self.bags / f'{name}_{k}'
        return path


# ----------------------------------------------------------------------------------------- protocol
class StudySession:
    """Where one participant stands in the protocol (derived from their files) and the steps that move it on.

    Thread-safe. Steps out of order raise StudyError (the page shows the text; nothing is written). A step
    whose own write fails (OSError, e.g. a full disk) is not taken: state and files stay as they were and the
    step can be tried again. Where the step's data was saved but its protocol.log line afterwards was not,
    the step stands and ``take_log_problem()`` says what is missing from the log.
    """

    def __init__(self, cfg: StudyConfig, config_text: str, root: str | Path, pid: str):
        self.cfg = cfg
        self.store = ParticipantStore(root, pid, cfg, config_text)
        self.pid = self.store.pid
        self.blocks = condition_order(self.pid, cfg.conditions)     # the condition of blocks 1, 2, ...
        self.order = order_name(self.pid, cfg.conditions)
        self._practice_goals = practice_goals(cfg, self.pid)
        self._lock = threading.RLock()
        self.active: LandingSpec | None = None
        self.last_feedback: dict[str, Any] | None = None
        self._log_problem: str | None = None
        try:
            self.store.log('session_opened', phase=self.phase, order=self.order, landings=len(self.store.rows))
        except BaseException:
            if self.store.created:
                self.store.discard()
            raise

    # ---------------------------------------------------------------- state
    def _note(self, event: str, **data: Any) -> None:
        """Log an event that follows a step already saved elsewhere: a failed write does not undo the step."""
        try:
            self.store.log(event, **data)
        except (OSError, StudyError) as exc:
            why = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
            problem = f'protocol.log event {event} not written ({why})'
            _LOG.error('participant %s: %s', self.pid, problem)
            self._log_problem = problem if self._log_problem is None else f'{self._log_problem}; {problem}'

    def take_log_problem(self) -> str | None:
        """What the last steps could not write to protocol.log (their data is saved), once; None if nothing."""
        with self._lock:
            problem, self._log_problem = self._log_problem, None
            return problem

    def _count(self, block: int) -> int:
        return sum(1 for r in self.store.rows if r['block'] == str(block))

    def _logged(self, event: str) -> bool:
        return any(e['event'] == event for e in self.store.events)

    @property
    def phase(self) -> str:
        """The current phase (``phases(cfg.n_blocks)``)."""
        with self._lock:
            if not self._logged('consent'):
                return 'consent'
            if self._count(PRACTICE_BLOCK) < self.cfg.practice_landings and not self._logged('practice_done'):
                return 'practice'
            for block in range(1, self.cfg.n_blocks + 1):
                if self._count(block) < self.cfg.landings_per_block:
                    return f'block{block}'
                if str(block) not in self.store.survey['sus']:
                    return f'sus{block}'
            return 'survey' if self.store.survey.get('survey') is None else 'done'

    def next_landing(self) -> LandingSpec:
        """The landing to fly next (practice or block); StudyError outside a landing phase."""
        with self._lock:
            phase = self.phase
            if phase == 'practice':
                k = self._count(PRACTICE_BLOCK)
                cond = self.cfg.practice_condition if self.cfg.practice_condition != 'first' else self.blocks[0]
                return LandingSpec(PRACTICE_BLOCK, cond, k, self._practice_goals[k])
            if phase.startswith('block'):
                block = phase_block(phase)
                k = self._count(block)
                return LandingSpec(block, self.blocks[block - 1], k, self.cfg.sequence[k])
            raise StudyError(f'no landing to fly now (the study is at {phase})')

    # ---------------------------------------------------------------- steps
    def consent(self) -> None:
        """The participant agreed to the consent text."""
        with self._lock:
            if self.phase != 'consent':
                raise StudyError('consent was given already')
            self.store.log('consent')

    def start_landing(self, bag: str | None = None) -> LandingSpec:
        """Mark the next landing as in flight (logged); returns what it flies."""
        with self._lock:
            if self.active is not None:
                raise StudyError(f'landing {self.active.name} is still in flight')
            spec = self.next_landing()
            self.store.log('landing_started', landing=spec.name, block=spec.block, condition=spec.condition,
                           trial=spec.trial, goal_index=spec.goal_index, bag=bag)
            self.active = spec              # only once logged: a failed write leaves no landing in flight
            self.last_feedback = None
            return spec

    def abort_landing(self, why: str) -> LandingSpec | None:
        """The landing in flight will not be recorded (page gone, no result): it is flown again next."""
        with self._lock:
            spec, self.active = self.active, None
            if spec is not None:
                self._note('landing_aborted', landing=spec.name, why=why)
            return spec

    def record_landing(self, landing: dict[str, Any], *, start_pad: int | None, episode: int | None,
                       bag: str | None, measures: dict[str, Any] | None = None) -> dict[str, str]:
        """Write the landing in flight's row from its /sim/landing result and its `measures` (MEASURE_COLUMNS;
        a measure missing or None is written empty: not measured); returns the stored row."""
        with self._lock:
            spec = self.active
            if spec is None:
                raise StudyError('no landing in flight')
            if int(landing.get('goal_index', -1)) != spec.goal_index:
                raise StudyError(f"landing result for goal pad {landing.get('goal_index')}, but {spec.name} flies "
                                 f'goal pad {spec.goal_index}')
            landed = landing.get('landed_index')
            row = {
                'participant': self.pid, 'block': spec.block, 'condition': spec.condition, 'order': self.order,
                'trial': spec.trial, 'goal_index': spec.goal_index, 'landed_index': landed,
                'nearest_index': landing.get('nearest_index'), 'error_m': landing.get('error_m'),
                'nearest_error_m': landing.get('nearest_error_m'), 'success': bool(landing.get('success')),
                'crash': bool(landing.get('crash')), 'outcome': landing.get('outcome', ''),
                'duration_s': landing.get('duration_s'),
                'started_on_pad': start_pad is not None and landed is not None and int(landed) == start_pad,
                'start_pad': start_pad, 'assist_live': landing.get('assisted'), 'episode': episode, 'bag': bag,
                'recorded_utc': time.strftime('%Y-%m-%dT%H:%M:%SZ', time.gmtime()),
                **{k: (measures or {}).get(k) for k in MEASURE_COLUMNS},
            }
            stored = self.store.append_row(row)
            self.active = None              # the row is saved: the landing is recorded whatever the log says
            self._note('landing_recorded', landing=spec.name, outcome=row['outcome'], episode=episode)
            if spec.block == PRACTICE_BLOCK and self._count(PRACTICE_BLOCK) >= self.cfg.practice_landings:
                self._note('practice_done', why='all practice landings flown')
            return stored

    def stop_practice(self) -> None:
        """The participant ends the practice early."""
        with self._lock:
            if self.phase != 'practice' or self.active is not None:
                raise StudyError('practice can be ended only between practice landings')
            self.store.log('practice_done', why='participant stopped practising',
                           landings=self._count(PRACTICE_BLOCK))

    def submit_sus(self, answers: Any) -> float:
        """SUS answers for the block just flown; returns its score."""
        with self._lock:
            phase = self.phase
            if not phase.startswith('sus'):
                raise StudyError(f'no SUS questionnaire now (the study is at {phase})')
            block = phase_block(phase)
            a = check_sus(answers)
            score = sus_score(a)
            survey = json.loads(json.dumps(self.store.survey))
            condition = self.blocks[block - 1]
            survey['sus'][str(block)] = {'condition': condition, 'answers': a, 'score': score}
            self.store.save_survey(survey)
            self._note('sus', block=block, condition=condition, score=score)
            return score

    def submit_survey(self, answers: Any) -> None:
        """The concluding survey's answers."""
        with self._lock:
            if self.phase != 'survey':
                raise StudyError(f'no concluding survey now (the study is at {self.phase})')
            survey = json.loads(json.dumps(self.store.survey))
            survey['survey'] = check_survey(answers)
            self.store.save_survey(survey)
            self._note('survey')
            self._note('done')

    # ---------------------------------------------------------------- page
    def view(self) -> dict[str, Any]:
        """What the station page shows (the 'study' message)."""
        with self._lock:
            phase = self.phase
            v: dict[str, Any] = {'type': 'study', 'participant': self.pid, 'phase': phase, 'order': self.order,
                                 'in_flight': self.active is not None, 'study': self.cfg.name}
            if phase == 'consent':
                v.update(intro=self.cfg.intro_text, consent=self.cfg.consent_text)
            elif phase == 'practice' or phase.startswith('block'):
                spec = self.active or self.next_landing()
                total = self.cfg.practice_landings if phase == 'practice' else self.cfg.landings_per_block
                v.update(trial=spec.trial + 1, of=total, condition=spec.condition, block=spec.block,
                         intro=self.cfg.intro_text, can_stop_practice=phase == 'practice' and self.active is None)
                if self.last_feedback is not None and phase == 'practice':
                    v['feedback'] = self.last_feedback
            elif phase.startswith('sus'):
                block = phase_block(phase)
                v.update(block=block, condition=self.blocks[block - 1], items=list(SUS_ITEMS))
            elif phase == 'survey':
                v.update(questions=[dict(q) for q in SURVEY])
            else:
                v.update(thanks=self.cfg.thanks_text)
            return v


def practice_feedback(landing: dict[str, Any], pads: np.ndarray | None, final_xy: Any | None) -> dict[str, Any]:
    """Practice feedback: where the drone ended relative to the goal pad (metres forward/left of its centre,
    in the odom frame's x/y) and whether it succeeded."""
    fb: dict[str, Any] = {'success': bool(landing.get('success')), 'crash': bool(landing.get('crash')),
                          'outcome': landing.get('outcome', ''), 'error_m': landing.get('error_m')}
    g = landing.get('goal_index')
    if pads is not None and final_xy is not None and _is_int(g) and 0 <= g < len(pads):
        d = np.asarray(final_xy, dtype=float)[:2] - np.asarray(pads[g], dtype=float)[:2]
        fb['offset_m'] = [round(float(d[0]), 2), round(float(d[1]), 2)]
    return fb


__all__ = ['ALL_CONDITIONS', 'ASSISTED_CONDITIONS', 'BASE_COLUMNS', 'CONDITIONS', 'CUE_CONDITION',
           'EXPERIENCE_QUESTIONS', 'LANDING_COLUMNS', 'MEASURE_COLUMNS', 'PHASES', 'PRACTICE_BLOCK', 'SURVEY',
           'SUS_ITEMS', 'KeyCounter', 'LandingSpec', 'ParticipantStore', 'StudyConfig', 'StudyError', 'StudySession',
           'block_condition', 'check_participant_id', 'check_survey', 'check_sus', 'condition_order',
           'first_condition', 'latin_square', 'order_name', 'participant_number', 'phase_block', 'phases',
           'practice_feedback', 'practice_goals', 'sus_score']
