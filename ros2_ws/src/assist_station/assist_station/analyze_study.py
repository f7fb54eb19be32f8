"""analyze_study: the paper's user-study analysis (Table I, tests, regressions, SUS, Figs. 6-8) of participant dirs,
and the per-landing measures of every condition with paired tests.

    analyze_study study_data/* --out study_analysis
    analyze_study study_sim/S01 study_sim/S02 --out /tmp/a --trajectories 4

Reads each participant directory the station (or simulate_study) wrote: study.yaml, landings.csv,
survey.json and bags/. Landings of the study's blocks count (practice does not); a landing that ended on
the pad the vehicle started above (``started_on_pad``, the paper's "immediately landing on the
starting platform") is excluded and counted per condition. A study has the paper's two conditions
(unassisted, assisted) or also assisted_cues (its study file's ``conditions``): the paper's figures
compare unassisted with assisted; the per-landing measures are reported for every condition.

Every value is checked against the study file and the protocol before it counts; what fails is left
out, one line each on stderr, and counted per reason in summary.json (``validation``) and in the
tables' first lines:

* the study file: the one most participant directories hold as study.yaml (ties: the first given),
  or --study; a participant that ran another sequence, scene, pad count, assistant or set of conditions
  is left out, as is one without study.yaml when --study is not given (a study file that does not parse,
  e.g. one naming an unknown condition, leaves its participant out with the reason);
* a participant directory is named after its participant (the station's layout): a name that is not
  a participant ID, or the same participant twice, is left out;
* landings.csv rows (study blocks; practice rows are not analysed): the participant, the block's
  condition and order (the participant's counterbalanced order: study.condition_order), the trial
  number (within the sequence) and its goal pad (the sequence's), finite errors within
  ``--max-error-m`` (the arena), the nearest pad's error no larger than the goal pad's, pad indices
  within the study's pads, an outcome the simulator writes that agrees with success and crash,
  ``assist_live`` (when recorded) agreeing with the condition (on in assisted and assisted_cues), a plain
  bag name, and the measures when recorded (a file written before them has none): ``path_length_m`` a
  finite length within ``MAX_PATH_M``, ``key_presses`` and ``corrective_keys`` integers as the station
  writes them, the corrective presses no more than the presses; a row written twice counts once, two
  different rows for one landing do not count. A torn last row (cut mid-write), a malformed CSV row (wrong number
  of fields, a field over the csv module's size limit) or a row that is not UTF-8 is skipped;
  a file without the station's columns, over 16 MB or unreadable leaves the participant out;
* survey.json: an object of the station's shape; each SUS entry's block (one of the study's) and
  condition (the participant's order), its ten answers (1-5) and score (0-100, the answers' score), and the
  concluding survey's 21 answers within each question's scale; a bad entry (or the whole file, when
  it is not an object, not UTF-8 JSON, or another participant's) is not used.

What is computed from the rows that pass:

* Table I (unassisted vs assisted), specified and nearest platform: success rate (specified: all legs on the goal pad;
  nearest: all legs on any pad, i.e. the pad nearest to where it landed), median and mean error, and
  variance (sample variance, m^2) of the horizontal error to the goal pad's centre (nearest: to the
  nearest pad's centre), unassisted vs assisted.
* Two-sample tests at the 99 % level (statistic and p for each; * in the table where p < 0.01):
  McNemar on success, paired by participant and trial (statsmodels; exact binomial when fewer than 25
  discordant pairs; landings without their pair are counted as ``unpaired``), Mood's median test
  (scipy), Welch's t-test on the mean (scipy), and the F-test of equal variances (variance ratio
  against scipy's F distribution, two-sided).
* The multivariable regression (statsmodels OLS) of a landing's error (unassisted and assisted landings)
  on three binary variables: assisted, first half (the earlier of the participant's unassisted and
  assisted blocks: block 1 in the two-block study) and experienced (a participant's mean self-rating on experience
  questions 2, 3, 5 and 6 at or above the threshold that makes a third of the participants
  experienced): coefficients and p-values.
* The experience level of the paper's Fig. 8: a linear regression (statsmodels OLS) of each
  participant's mean unassisted error on their answers to questions 2, 3, 5 and 6 predicts the error
  expected for that experience; the prediction scaled to 0..1 and inverted is the experience level
  (0 novice, 1 expert). With fewer participants than the regression has terms plus two, the mean
  rating scaled to 0..1 stands in (said in summary.json). Each condition's per-participant median
  error is then fitted against it (one line per condition, slope reported).
* SUS: mean score per condition and its percentile on the Sauro-Lewis curved grading scale (linear
  between the grade boundaries; 68 is the 50th percentile).
* Goal inference (assisted landings): the share that ended nearest to the goal pad, and the share
  of those that succeeded (the paper: 79.34 % and 93.34 %).
* Per-landing measures (``measures`` in summary.json, the second table), per condition of the study: landings,
  success rate, wrong-pad rate (outcome wrong_pad: all legs on another pad), and the mean and median per
  landing of time to land (``duration_s``: the episode's start to its landing, sim seconds), path length
  (``path_length_m``: the /odom path flown), corrective key presses and key presses (study.KeyCounter
  defines them); a landing without a measure (not recorded) is left out of that measure only. Between
  each pair of conditions the data have (both with landings), paired by participant: the Wilcoxon
  signed-rank test (scipy, two-sided; exact for small samples without ties) on the participants'
  per-condition means of each continuous measure, and McNemar's test (as above) on success and on
  wrong-pad, landings paired by participant and trial. * marks p < 0.01 (not corrected for the three
  comparisons of a three-condition study).

Writes OUT/summary.json (strict JSON: a figure that is not defined is null), OUT/table.txt,
OUT/table.md, OUT/violin.png (Fig. 6), OUT/experience.png (Fig. 8) and OUT/trajectories.png (Fig. 7:
chosen landings' /odom tracks from their bags, both conditions of the same trials). Existing outputs
in OUT are never overwritten, nor is anything written through a symbolic link there: the tool refuses
before any work, and each file is published only where nothing (not even a dangling link) stands.

Exit status: 0 when the analysis was written (rows, files or participants left out are reported, not
fatal), 1 when nothing could be analysed or an output cannot be written (what was written stays),
2 for bad arguments.
"""
from __future__ import annotations

import csv
import io
import json
import logging
import math
import os
import re
import secrets
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from assist_common.atomic import fsync_dir
from assist_common.frames import heading, rotate_xy
from assist_common.settings import parse_command, setting

from .study import (ASSISTED_CONDITIONS, BASE_COLUMNS, CONDITIONS, CUE_CONDITION, EXPERIENCE_QUESTIONS,
                    PARTICIPANT_ID, StudyConfig, StudyError, block_condition, check_survey, check_sus,
                    condition_order, order_name, sus_score)

log = logging.getLogger('analyze_study')
ALPHA = 0.01
OUTPUTS = ('summary.json', 'table.txt', 'table.md', 'violin.png', 'experience.png', 'trajectories.png')
# Sauro & Lewis curved grading scale: (SUS score, percentile rank) at the grade boundaries, F .. A+
SUS_PERCENTILES = ((0.0, 0.0), (51.6, 14.0), (51.7, 15.0), (62.6, 34.0), (62.7, 35.0), (64.9, 40.0), (65.0, 41.0),
                   (71.0, 59.0), (71.1, 60.0), (72.5, 64.0), (72.6, 65.0), (74.0, 69.0), (74.1, 70.0), (77.1, 79.0),
                   (77.2, 80.0), (78.8, 84.0), (78.9, 85.0), (80.7, 89.0), (80.8, 90.0), (84.0, 95.0), (84.1, 96.0),
                   (100.0, 100.0))
JUMP_M = 1.0          # an /odom step longer than this between two messages is a reset (teleport)
COLORS = {'unassisted': '#1f77b4', 'assisted': '#2ca02c', CUE_CONDITION: '#d62728'}

# what the data are checked against
OUTCOMES = ('success', 'wrong_pad', 'edge', 'crash', 'timeout')     # the simulator's landing outcomes
PROTOCOL_FIELDS = ('scene_seed', 'sequence', 'n_pads', 'assistant_mode', 'policy_model', 'encoder_model',
                   'conditions')
SUS_MAX = 100.0
SUS_STEP = 2.5                          # ten 1-5 answers give scores in steps of 2.5
STORED_TOLERANCE_M = 1e-3               # landings.csv stores metres with four decimals
MAX_DURATION_S = 24 * 3600.0
MAX_PATH_M = 100_000.0                  # a landing's path flown (m): far beyond any landing, below any corruption
MAX_KEY_PRESSES = 1_000_000
MAX_LANDINGS_BYTES = 16 * 1024 * 1024   # a study's landings.csv holds a few dozen rows of ~200 bytes
MAX_SURVEY_BYTES = 1024 * 1024
MAX_DETAILS = 200                       # excluded rows listed one by one (log and summary.json); the rest counted
INTEGER = re.compile(r'-?[0-9]{1,18}')
SHOWN_CHARS = 60                        # a value from a file is quoted (repr) at most this long

# why a study row is left out (summary.json validation.rows_excluded keys)
R_TORN = 'torn last row'
R_MALFORMED = 'malformed CSV row'
R_ENCODING = 'not UTF-8'
R_PARTICIPANT = "another participant's row"
R_BLOCK = "block not 0 (practice) or one of the study's blocks"
R_CONDITION = "condition or order contradicts the participant's order"
R_TRIAL = 'trial outside the sequence'
R_GOAL = "goal pad differs from the sequence's"
R_VALUE = 'unreadable or out-of-range value'
R_ERROR = 'error not finite or outside the arena'
R_OUTCOME = 'outcome inconsistent with success, crash or errors'
R_LIVE = 'assist_live contradicts the condition'
R_DUPLICATE = 'duplicate row'
R_CONFLICT = 'conflicting rows for one landing'


@dataclass
class AnalyzeArgs:
    """Command-line arguments of analyze_study (besides the participant directories)."""

    out: str = setting('study_analysis', nonempty=True)
    trajectories: int = setting(3, ge=0, le=50)
    plots: bool = True
    study: str = ''
    max_error_m: float = setting(50.0, gt=0.0, le=10000.0)


HELP = {'out': 'directory for summary.json, the tables and the figures (created; existing outputs are refused)',
        'trajectories': 'participants whose landings Fig. 7 draws (both conditions of one trial each; 0: no figure)',
        'plots': 'draw the figures',
        'study': 'study file the data are checked against (default: the study.yaml most participant directories '
                 'hold)',
        'max_error_m': 'largest credible landing error (m): the arena\'s extent (the simulator\'s 5-pad room is '
                       'under 40 m corner to corner); larger errors are left out as invalid'}


# ----------------------------------------------------------------------------------------- loading
def _bool(text: str) -> bool | None:
    return {'true': True, 'false': False}.get(text.strip().lower())


def _float(text: Any) -> float | None:
    try:
        v = float(text)
    except (TypeError, ValueError, OverflowError):
        return None
    return v if math.isfinite(v) else None


def _int(text: str) -> int | None:
    """A decimal integer as the station writes it ('-'? digits, at most 18 of them), else None."""
    if not isinstance(text, str) or not INTEGER.fullmatch(text):
        return None
    return int(text)


def _number(v: Any) -> bool:
    """A finite JSON number (not a bool)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _shown(v: Any) -> str:
    """A value from a file as it may appear in a log line: repr, cut short."""
    text = repr(v)
    return text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS - 3] + '...'


def _printable(line: str) -> str:
    """`line` with every character that is not printable (newlines, controls, undecodable bytes) escaped, so a
    name or value from a file can neither forge a log line nor break the tables' encoding."""
    return line if line.isprintable() else ''.join(c if c.isprintable() else ascii(c)[1:-1] for c in line)


@dataclass
class Participant:
    """One participant's landings (study blocks only) and answers."""

    pid: str
    dir: Path
    rows: list[dict[str, Any]]
    sus: dict[str, float]                 # condition -> score
    survey: dict[str, Any] | None
    conditions: tuple[str, ...] = CONDITIONS      # the study's conditions (one block each)


@dataclass
class Validation:
    """What the analysis left out and why: rows counted per reason, files and participants one line each."""

    rows: Counter = field(default_factory=Counter)
    files: list[str] = field(default_factory=list)
    participants: list[str] = field(default_factory=list)
    details: list[str] = field(default_factory=list)
    details_left_off: int = 0

    def row(self, where: str, reason: str, detail: str = '') -> None:
        """Count one excluded row; the first MAX_DETAILS are logged and listed."""
        self.rows[reason] += 1
        self._note(_printable(f'{where}: {reason}' + (f' ({detail})' if detail else '') + '; row left out'))

    def file(self, where: str, why: str) -> None:
        """One file (or one entry of it) that is not used."""
        line = _printable(f'{where}: {why}; not used')
        self.files.append(line)
        log.warning('%s', line)

    def participant(self, where: str, why: str) -> None:
        """One participant directory that is left out."""
        line = _printable(f'{where}: {why}; participant left out')
        self.participants.append(line)
        log.warning('%s', line)

    def _note(self, line: str) -> None:
        if len(self.details) < MAX_DETAILS:
            self.details.append(line)
            log.warning('%s', line)
        else:
            if not self.details_left_off:
                log.warning('more rows left out: counted in summary.json (validation.rows_excluded), not listed')
            self.details_left_off += 1

    def as_dict(self) -> dict[str, Any]:
        """summary.json's ``validation`` entry."""
        return {'rows_excluded': dict(sorted(self.rows.items())), 'rows_excluded_total': sum(self.rows.values()),
                'files_excluded': list(self.files), 'participants_excluded': list(self.participants),
                'rows_listed': list(self.details), 'rows_not_listed': self.details_left_off}


def protocol_of(cfg: StudyConfig) -> tuple:
    """The settings that define what a study measures (two participants are comparable when these agree)."""
    return tuple(getattr(cfg, f) for f in PROTOCOL_FIELDS)


def _protocol_difference(cfg: StudyConfig, ref: StudyConfig) -> str:
    return ', '.join(f for f in PROTOCOL_FIELDS if getattr(cfg, f) != getattr(ref, f))


def read_csv_rows(path: Path, val: Validation, where: str) -> tuple[list[str], list[tuple[int, list[str]]]]:
    """(header, [(line, fields)]) of a CSV file; torn, malformed and non-UTF-8 rows are counted in `val` and
    skipped. StudyError (one line) when the file as a whole cannot be used."""
    try:
        size = path.stat().st_size
        if size > MAX_LANDINGS_BYTES:
            raise StudyError(f'{path}: {size} bytes, more than a study writes ({MAX_LANDINGS_BYTES} at most)')
        raw = path.read_bytes()
    except OSError as exc:
        raise StudyError(f'{path}: cannot read ({exc.strerror or exc})') from None
    if raw and not raw.endswith(b'\n'):            # a row cut mid-write (the station drops it on resume)
        cut = raw.rfind(b'\n') + 1
        if cut:
            line = raw.count(b'\n', 0, cut) + 1
            val.row(f'{where} line {line}', R_TORN, f'{len(raw) - cut} bytes without a line end')
        raw = raw[:cut]
    text = raw.decode('utf-8', errors='surrogateescape')
    reader = csv.reader(io.StringIO(text, newline=''), strict=True)
    header: list[str] | None = None
    rows: list[tuple[int, list[str]]] = []
    while True:
        start = reader.line_num + 1
        try:
            fields_ = next(reader)
        except StopIteration:
            break
        except csv.Error as exc:
            if header is None:
                raise StudyError(f'{path}: the header is not CSV ({exc})') from None
            val.row(f'{where} line {start}', R_MALFORMED, str(exc))
            continue
        if not fields_:
            continue                                # a blank line
        utf8 = not any('\udc80' <= ch <= '\udcff' for f in fields_ for ch in f)
        if header is None:
            if not utf8:
                raise StudyError(f'{path}: the header is not UTF-8')
            header = fields_
            missing = [c for c in BASE_COLUMNS if c not in header]
            if missing or len(set(header)) != len(header):
                raise StudyError(f'{path}: not the station\'s columns (missing {", ".join(missing) or "none"}'
                                 f'{", some twice" if len(set(header)) != len(header) else ""})')
            continue
        if not utf8:
            val.row(f'{where} line {start}', R_ENCODING)
        elif len(fields_) != len(header):
            val.row(f'{where} line {start}', R_MALFORMED, f'{len(fields_)} fields, the header has {len(header)}')
        else:
            rows.append((start, fields_))
    if header is None:
        raise StudyError(f'{path}: empty (no header)')
    return header, rows


def _optional_int(text: str, lo: int, hi: int) -> tuple[bool, int | None]:
    """(valid, value) of an optional integer field in lo..hi-1 ('' is None)."""
    if text == '':
        return True, None
    v = _int(text)
    return (v is not None and lo <= v < hi), v


def _measure_problem(r: dict[str, str]) -> str | None:
    """Why a row's recorded measures cannot be used (None: they can; an empty or absent one was not recorded)."""
    path = r.get('path_length_m', '')
    if path != '':
        v = _float(path)
        if v is None or not 0.0 <= v <= MAX_PATH_M:
            return f'path_length_m {_shown(path)} (0-{MAX_PATH_M:g} m)'
    counts = {}
    for name in ('key_presses', 'corrective_keys'):
        text = r.get(name, '')
        if text != '':
            counts[name] = _int(text)
            if counts[name] is None or not 0 <= counts[name] <= MAX_KEY_PRESSES:
                return f'{name} {_shown(text)} (an integer 0-{MAX_KEY_PRESSES})'
    if len(counts) == 2 and counts['corrective_keys'] > counts['key_presses']:
        return f"corrective_keys {counts['corrective_keys']} > key_presses {counts['key_presses']}"
    return None


def check_row(r: dict[str, str], pid: str, cfg: StudyConfig, max_error_m: float) -> tuple[str | None, str]:
    """(reason, detail) why a study-block row of participant `pid` cannot count (None: it can)."""
    if r['participant'] != pid:
        return R_PARTICIPANT, f"participant {_shown(r['participant'])}"
    block = _int(r['block'])
    expected = block_condition(pid, block, cfg.conditions) if block in range(1, cfg.n_blocks + 1) else None
    order = order_name(pid, cfg.conditions)
    if r['condition'] != expected or r['order'] not in ('', order):
        return R_CONDITION, (f"block {block} is {_shown(r['condition'])}, order {_shown(r['order'])}; {pid} flies "
                             f'{expected} in block {block} ({order})')
    trial = _int(r['trial'])
    if trial is None or not 0 <= trial < len(cfg.sequence):
        return R_TRIAL, f"trial {_shown(r['trial'])}, the sequence has {len(cfg.sequence)}"
    if _int(r['goal_index']) != cfg.sequence[trial]:
        return R_GOAL, f"goal pad {_shown(r['goal_index'])}, the sequence's trial {trial} is {cfg.sequence[trial]}"
    for name in ('success', 'crash', 'started_on_pad'):
        if _bool(r[name]) is None:
            return R_VALUE, f'{name} {_shown(r[name])}'
    for name in ('landed_index', 'nearest_index', 'start_pad'):
        ok, _ = _optional_int(r[name], 0, cfg.n_pads)
        if not ok:
            return R_VALUE, f'{name} {_shown(r[name])} (pads 0..{cfg.n_pads - 1})'
    ok, _ = _optional_int(r['episode'], 0, 2 ** 63)
    if not ok:
        return R_VALUE, f"episode {_shown(r['episode'])}"
    if r['duration_s'] != '':
        d = _float(r['duration_s'])
        if d is None or not 0.0 <= d <= MAX_DURATION_S:
            return R_VALUE, f"duration_s {_shown(r['duration_s'])}"
    if r['assist_live'] != '' and _bool(r['assist_live']) is None:
        return R_VALUE, f"assist_live {_shown(r['assist_live'])}"
    why = _measure_problem(r)
    if why:
        return R_VALUE, why
    bag = r['bag']
    if bag in ('.', '..') or any(c in bag for c in '/\\\0'):
        return R_VALUE, f'bag {_shown(bag)} (a name under bags/)'
    err = _float(r['error_m'])
    nerr = _float(r['nearest_error_m']) if r['nearest_error_m'] != '' else err
    for name, v in (('error_m', err), ('nearest_error_m', nerr)):
        if v is None or not 0.0 <= v <= max_error_m:
            return R_ERROR, f'{name} {_shown(r[name])} (0-{max_error_m:g} m)'
    outcome, success, crash = r['outcome'], _bool(r['success']), _bool(r['crash'])
    if (outcome not in OUTCOMES or success != (outcome == 'success') or crash != (outcome == 'crash')
            or (success and _int(r['landed_index']) != cfg.sequence[trial])
            or nerr > err + STORED_TOLERANCE_M):
        return R_OUTCOME, (f"outcome {_shown(outcome)}, success {r['success']}, crash {r['crash']}, landed_index "
                           f"{_shown(r['landed_index'])}, error_m {err:g}, nearest_error_m {nerr:g}")
    live = _bool(r['assist_live']) if r['assist_live'] != '' else None
    if live is not None and live != (r['condition'] in ASSISTED_CONDITIONS):
        return R_LIVE, f"assist_live {r['assist_live']} in a {r['condition']} block"
    return None, ''


def load_rows(path: Path, pid: str, cfg: StudyConfig, val: Validation, max_error_m: float) -> list[dict[str, Any]]:
    """The study-block rows of `pid`'s landings.csv that pass every check (see the module's doc); the others are
    counted in `val`. StudyError when the file cannot be used at all."""
    where = f'{pid}/landings.csv'
    header, raw_rows = read_csv_rows(path, val, where)
    passed: dict[tuple[int, int], list[tuple[int, dict[str, str]]]] = {}
    for line, fields_ in raw_rows:
        r = dict(zip(header, fields_))
        block = _int(r['block'])
        if block == 0:
            continue                                    # practice: not analysed
        if block not in range(1, cfg.n_blocks + 1):
            val.row(f'{where} line {line}', R_BLOCK, f"block {_shown(r['block'])}")
            continue
        reason, detail = check_row(r, pid, cfg, max_error_m)
        if reason is not None:
            val.row(f'{where} line {line}', reason, detail)
            continue
        passed.setdefault((block, int(r['trial'])), []).append((line, r))
    rows = []
    for (block, trial), same in sorted(passed.items()):
        first_line, r = same[0]
        others = same[1:]
        if any(o != r for _, o in others):
            for line, _ in same:
                val.row(f'{where} line {line}', R_CONFLICT, f'block {block} trial {trial} is on lines '
                        + ', '.join(str(n) for n, _ in same))
            continue
        for line, _ in others:
            val.row(f'{where} line {line}', R_DUPLICATE, f'same as line {first_line}')
        err = float(r['error_m'])
        rows.append({'pid': pid, 'block': block, 'condition': r['condition'], 'trial': trial,
                     'goal_index': int(r['goal_index']), 'landed_index': _int(r['landed_index']),
                     'nearest_index': _int(r['nearest_index']), 'error_m': err,
                     'nearest_error_m': float(r['nearest_error_m']) if r['nearest_error_m'] != '' else err,
                     'success': bool(_bool(r['success'])), 'crash': bool(_bool(r['crash'])), 'outcome': r['outcome'],
                     'started_on_pad': bool(_bool(r['started_on_pad'])), 'bag': r['bag'], 'line': first_line,
                     'duration_s': _float(r['duration_s']) if r['duration_s'] != '' else None,
                     'path_length_m': _float(r['path_length_m']) if r.get('path_length_m', '') != '' else None,
                     'key_presses': _int(r['key_presses']) if r.get('key_presses', '') != '' else None,
                     'corrective_keys': _int(r['corrective_keys']) if r.get('corrective_keys', '') != '' else None})
    return rows


def _refuse_constant(name: str) -> None:
    raise ValueError(f'{name} is not a JSON number')


def load_answers(path: Path, pid: str, val: Validation,
                 conditions: tuple[str, ...] = CONDITIONS) -> tuple[dict[str, float], dict[str, Any] | None]:
    """(SUS score per condition, the concluding survey's answers or None) from survey.json; what does not pass
    the station's own checks (study.check_sus, check_survey, the participant's order over `conditions`) is
    reported in `val`."""
    where = f'{pid}/survey.json'
    try:
        if path.stat().st_size > MAX_SURVEY_BYTES:
            val.file(where, f'larger than {MAX_SURVEY_BYTES} bytes')
            return {}, None
        data = json.loads(path.read_bytes().decode('utf-8'), parse_constant=_refuse_constant)
    except OSError as exc:
        val.file(where, f'cannot read ({exc.strerror or exc})')
        return {}, None
    except UnicodeDecodeError:
        val.file(where, 'not UTF-8')
        return {}, None
    except (ValueError, RecursionError) as exc:
        val.file(where, f'not JSON ({str(exc).splitlines()[0][:120]})')
        return {}, None
    if not isinstance(data, dict):
        val.file(where, f'a JSON {type(data).__name__}, not the station\'s object')
        return {}, None
    if 'participant' in data and data['participant'] != pid:
        val.file(where, f"answers of participant {_shown(data['participant'])}")
        return {}, None
    sus: dict[str, float] = {}
    entries = data.get('sus', {})
    if not isinstance(entries, dict):
        val.file(f'{where} sus', f'a JSON {type(entries).__name__}, not an object keyed by block')
        entries = {}
    for block, entry in entries.items():
        why = _sus_problem(pid, block, entry, conditions)
        if why:
            val.file(f'{where} sus block {_shown(block)}', why)
            continue
        score = sus_score(entry['answers']) if 'answers' in entry else float(entry['score'])
        sus[entry['condition']] = float(score)
    survey = data.get('survey')
    if survey is not None:
        try:
            survey = check_survey(survey)
        except StudyError as exc:
            val.file(where, str(exc))
            survey = None
    return sus, survey


def _sus_problem(pid: str, block: Any, entry: Any, conditions: tuple[str, ...] = CONDITIONS) -> str | None:
    """Why one survey.json SUS entry cannot be used (None: it can)."""
    blocks = [str(b) for b in range(1, len(conditions) + 1)]
    if block not in blocks:
        return f"SUS is asked after block {' or '.join([', '.join(blocks[:-1]), blocks[-1]])} only"
    if not isinstance(entry, dict):
        return f'a JSON {type(entry).__name__}, not an object'
    expected = block_condition(pid, int(block), conditions)
    if entry.get('condition') != expected:
        return f"condition {_shown(entry.get('condition'))}, {pid} flies {expected} in block {block}"
    score = entry.get('score')
    if 'answers' in entry:
        try:
            answers = check_sus(entry['answers'])
        except StudyError as exc:
            return str(exc)
        if score is not None and not (_number(score) and abs(score - sus_score(answers)) < 1e-9):
            return f'score {_shown(score)} is not the answers\' score {sus_score(answers):g}'
        return None
    if not (_number(score) and 0.0 <= score <= SUS_MAX and float(score / SUS_STEP).is_integer()):
        return f'score {_shown(score)}: a SUS score is 0-{SUS_MAX:g} in steps of {SUS_STEP:g}'
    return None


def load_participant(path: Path, pid: str, cfg: StudyConfig, val: Validation,
                     max_error_m: float = AnalyzeArgs.max_error_m) -> Participant:
    """Participant `pid`'s checked rows and answers from directory `path`; StudyError (one line) when its
    landings.csv cannot be used at all."""
    rows = load_rows(path / 'landings.csv', pid, cfg, val, max_error_m)
    sus: dict[str, float] = {}
    survey = None
    if (path / 'survey.json').exists():
        sus, survey = load_answers(path / 'survey.json', pid, val, cfg.conditions)
    return Participant(pid, path, rows, sus, survey, cfg.conditions)


def load_study(dirs: list[Path], args: AnalyzeArgs, val: Validation) -> list[Participant]:
    """Every usable participant of `dirs`, checked against one study file (see the module's doc); the rest is
    reported in `val`. StudyError when --study cannot be read."""
    found: list[tuple[Path, str, StudyConfig | None]] = []
    seen: dict[str, Path] = {}
    for d in dirs:
        pid = Path(os.path.abspath(d)).name
        if not d.is_dir():
            val.participant(str(d), 'not a directory')
            continue
        if not (d / 'landings.csv').exists():
            val.participant(str(d), 'no landings.csv (not a participant directory)')
            continue
        if not PARTICIPANT_ID.fullmatch(pid):
            val.participant(str(d), f'{_shown(pid)} is not a participant ID (a directory is named after its '
                                    'participant)')
            continue
        if pid in seen:
            val.participant(str(d), f'participant {pid} is given twice (also {seen[pid]})')
            continue
        seen[pid] = d
        cfg = None
        if (d / 'study.yaml').exists():
            try:
                cfg, _ = StudyConfig.load(d / 'study.yaml')
            except StudyError as exc:
                val.participant(str(d), str(exc))
                continue
        found.append((d, pid, cfg))
    if args.study:
        ref, _ = StudyConfig.load(args.study)
    else:
        protocols = Counter(protocol_of(c) for _, _, c in found if c is not None)
        if not protocols:
            for d, _, _ in found:
                val.participant(str(d), 'no study.yaml (give --study FILE)')
            return []
        top = protocols.most_common(1)[0][0]
        ref = next(c for _, _, c in found if c is not None and protocol_of(c) == top)
    parts = []
    for d, pid, cfg in found:
        if cfg is None and not args.study:
            val.participant(str(d), 'no study.yaml (give --study FILE)')
            continue
        if cfg is not None and protocol_of(cfg) != protocol_of(ref):
            val.participant(str(d), f'ran another study file ({_protocol_difference(cfg, ref)} differ)')
            continue
        try:
            p = load_participant(d, pid, ref, val, args.max_error_m)
        except StudyError as exc:
            val.participant(str(d), str(exc))
            continue
        if not p.rows and not p.sus:
            val.participant(str(d), 'no study landing or SUS answer passes the checks')
            continue
        parts.append(p)
    return parts


# ----------------------------------------------------------------------------------------- statistics
def sus_percentile(score: float) -> float:
    """Percentile rank of a SUS score (Sauro-Lewis curved grading scale, linear between boundaries)."""
    xs, ys = zip(*SUS_PERCENTILES)
    return float(np.interp(score, xs, ys))


def describe(errors: np.ndarray, success: np.ndarray) -> dict[str, float | None]:
    """Success rate, median, mean and sample variance of one condition's landings."""
    if errors.size == 0:
        return {'success_rate': None, 'median_error_m': None, 'mean_error_m': None, 'variance_m2': None}
    return {'success_rate': float(np.mean(success)), 'median_error_m': float(np.median(errors)),
            'mean_error_m': float(np.mean(errors)),
            'variance_m2': float(np.var(errors, ddof=1)) if errors.size > 1 else None}


def mcnemar_test(pairs: list[tuple[bool, bool]]) -> dict[str, float | None]:
    """McNemar's test on paired successes (unassisted, assisted): exact binomial below 25 discordant pairs."""
    from statsmodels.stats.contingency_tables import mcnemar
    if not pairs:
        return {'statistic': None, 'p': None, 'pairs': 0}
    a = np.array(pairs, dtype=bool)
    table = [[int(np.sum(a[:, 0] & a[:, 1])), int(np.sum(a[:, 0] & ~a[:, 1]))],
             [int(np.sum(~a[:, 0] & a[:, 1])), int(np.sum(~a[:, 0] & ~a[:, 1]))]]
    discordant = table[0][1] + table[1][0]
    exact = discordant < 25
    res = mcnemar(table, exact=exact, correction=True)
    return {'statistic': float(res.statistic), 'p': float(res.pvalue), 'pairs': len(pairs),
            'discordant': discordant, 'exact': exact, 'table': table}


def two_sample_tests(un: np.ndarray, asd: np.ndarray) -> dict[str, dict[str, float | None]]:
    """Mood's median test, Welch's t-test and the two-sided F-test of equal variances."""
    from scipy import stats
    none = {'statistic': None, 'p': None}
    out = {'mood_median': dict(none), 't': dict(none), 'f': dict(none)}
    if un.size < 2 or asd.size < 2:
        return out
    try:
        stat, p, _, _ = stats.median_test(un, asd)
        out['mood_median'] = {'statistic': float(stat), 'p': float(p)}
    except ValueError as exc:            # every value on one side of the grand median
        log.warning("Mood's median test not defined here: %s", exc)
    t = stats.ttest_ind(un, asd, equal_var=False)
    out['t'] = {'statistic': float(t.statistic), 'p': float(t.pvalue)}
    v_un, v_as = np.var(un, ddof=1), np.var(asd, ddof=1)
    if v_as > 0 and v_un > 0:
        f = v_un / v_as
        d1, d2 = un.size - 1, asd.size - 1
        p = 2.0 * min(stats.f.cdf(f, d1, d2), stats.f.sf(f, d1, d2))
        out['f'] = {'statistic': float(f), 'p': float(min(1.0, p))}
    return out


def experience_ratings(parts: list[Participant]) -> dict[str, np.ndarray]:
    """Each participant's answers to the experience questions (2, 3, 5, 6), for those who answered."""
    out = {}
    for p in parts:
        if p.survey is None:
            continue
        vals = [_float(p.survey.get(str(q))) for q in EXPERIENCE_QUESTIONS]
        if all(v is not None for v in vals):
            out[p.pid] = np.array(vals, dtype=float)
    return out


def experienced_set(ratings: dict[str, np.ndarray]) -> tuple[set[str], float | None]:
    """Participants rated experienced: mean rating at or above the threshold that makes the number experienced
    closest to a third (ratings tie, so it is rarely exactly a third)."""
    if not ratings:
        return set(), None
    means = {pid: float(np.mean(r)) for pid, r in ratings.items()}
    target = len(means) / 3.0            # ratings tie: the threshold whose count comes closest to a third

    def miss(c: float) -> tuple[float, float]:
        return abs(sum(m >= c for m in means.values()) - target), -c
    threshold = min(set(means.values()), key=miss)
    return {pid for pid, m in means.items() if m >= threshold}, threshold


def first_half_block(pid: str, conditions: tuple[str, ...] = CONDITIONS) -> int:
    """The earlier of participant `pid`'s unassisted and assisted blocks (the regression's first half: block 1
    in the two-block study)."""
    order = condition_order(pid, conditions)
    return 1 + min(order.index(c) for c in CONDITIONS)


def regression(rows: list[dict], experienced: set[str],
               conditions: tuple[str, ...] = CONDITIONS) -> dict[str, dict[str, float | None]]:
    """OLS of error_m on assisted, first_half and experienced (binary); coefficient and p-value of each. `rows`:
    unassisted and assisted landings; first_half: the row's block is the earlier of its participant's two."""
    import pandas as pd
    import statsmodels.formula.api as smf
    df = pd.DataFrame({'error_m': [r['error_m'] for r in rows],
                       'assisted': [int(r['condition'] == 'assisted') for r in rows],
                       'first_half': [int(r['block'] == first_half_block(r['pid'], conditions)) for r in rows],
                       'experienced': [int(r['pid'] in experienced) for r in rows]})
    out: dict[str, dict[str, float | None]] = {}
    terms = [t for t in ('assisted', 'first_half', 'experienced') if df[t].nunique() > 1]
    design = np.column_stack([np.ones(len(df))] + [df[t].to_numpy(float) for t in terms]) if terms else None
    if not terms or len(df) <= len(terms) + 1 or np.linalg.matrix_rank(design) < design.shape[1]:
        why = 'too few landings, or the variables are collinear in these data (e.g. one order only)'
        return {t: {'coef': None, 'p': None, 'note': why} for t in ('assisted', 'first_half', 'experienced')}
    fit = smf.ols('error_m ~ ' + ' + '.join(terms), data=df).fit()
    for t in ('assisted', 'first_half', 'experienced'):
        out[t] = ({'coef': float(fit.params[t]), 'p': float(fit.pvalues[t])} if t in terms
                  else {'coef': None, 'p': None, 'note': 'constant in these data'})
    out['intercept'] = {'coef': float(fit.params['Intercept']), 'p': float(fit.pvalues['Intercept'])}
    out['n'] = {'coef': float(len(df)), 'p': None}
    return out


def experience_levels(parts: list[Participant], ratings: dict[str, np.ndarray]) -> tuple[dict[str, float], str]:
    """Fig. 8's experience level per participant (0 novice .. 1 expert) and how it was obtained."""
    import statsmodels.api as sm
    pids = [p.pid for p in parts if p.pid in ratings]
    mean_err = {}
    for p in parts:
        errs = [r['error_m'] for r in p.rows if r['condition'] == 'unassisted' and not r['started_on_pad']]
        if p.pid in ratings and errs:
            mean_err[p.pid] = float(np.mean(errs))
    pids = [pid for pid in pids if pid in mean_err]
    if not pids:
        return {}, 'no participant with both survey answers and unassisted landings'
    X = np.array([ratings[pid] for pid in pids])
    y = np.array([mean_err[pid] for pid in pids])
    if len(pids) >= X.shape[1] + 3:
        fit = sm.OLS(y, sm.add_constant(X, has_constant='add')).fit()
        pred = fit.predict(sm.add_constant(X, has_constant='add'))
        span = pred.max() - pred.min()
        level = 1.0 - (pred - pred.min()) / span if span > 0 else np.full(len(pids), 0.5)
        how = 'regression of mean unassisted error on questions 2, 3, 5, 6 (prediction scaled to 0..1, inverted)'
    else:
        m = X.mean(axis=1)
        level = (m - 1.0) / 4.0
        how = 'mean rating of questions 2, 3, 5, 6 scaled to 0..1 (too few participants for the regression)'
    return {pid: float(v) for pid, v in zip(pids, level)}, how


def line_fit(x: np.ndarray, y: np.ndarray) -> dict[str, float | None]:
    """Least-squares line y = intercept + slope x (statsmodels OLS)."""
    import statsmodels.api as sm
    if x.size < 2 or np.ptp(x) == 0:
        return {'slope': None, 'intercept': None}
    fit = sm.OLS(y, sm.add_constant(x, has_constant='add')).fit()
    return {'slope': float(fit.params[1]), 'intercept': float(fit.params[0]),
            'p': float(fit.pvalues[1]) if x.size > 2 else None}


# ----------------------------------------------------------------------------------------- measures
# the continuous per-landing measures: (summary.json key, row key, table label, name in the tests' lines)
MEASURES = (('time_to_land_s', 'duration_s', 'Time to land (s)', 'time to land'),
            ('path_length_m', 'path_length_m', 'Path length (m)', 'path length'),
            ('corrective_keys', 'corrective_keys', 'Corrective key presses', 'corrective keys'),
            ('key_presses', 'key_presses', 'Key presses', 'key presses'))
RATES = (('success', 'Success rate', 'success'), ('wrong_pad', 'Wrong-pad rate', 'wrong pad'))


def _rate_hit(rate: str, r: dict[str, Any]) -> bool:
    """Whether landing `r` counts for `rate`: success (all legs on the goal pad) or wrong_pad (on another pad)."""
    return bool(r['success']) if rate == 'success' else r['outcome'] == 'wrong_pad'


def wilcoxon_test(a: np.ndarray, b: np.ndarray) -> dict[str, Any]:
    """Wilcoxon signed-rank test (two-sided, scipy) of paired values a, b: statistic (the smaller rank sum), p,
    pairs and the median of a - b; statistic and p None when no pair differs."""
    from scipy import stats
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    out: dict[str, Any] = {'statistic': None, 'p': None, 'pairs': int(d.size),
                           'median_difference': float(np.median(d)) if d.size else None}
    if not np.any(d != 0):
        return out
    res = stats.wilcoxon(a, b)
    out.update(statistic=float(res.statistic), p=float(res.pvalue))
    return out


def measures(rows: list[dict[str, Any]], conditions: tuple[str, ...]) -> dict[str, Any]:
    """summary.json's ``measures``: per condition its landings, success and wrong-pad rates and each continuous
    measure's mean and median per landing; per pair of conditions with landings, the paired tests (module doc)."""
    by = {c: [r for r in rows if r['condition'] == c] for c in conditions}
    per: dict[str, dict[str, Any]] = {}
    for c in conditions:
        entry: dict[str, Any] = {'landings': len(by[c])}
        for rate, *_ in RATES:
            entry[f'{rate}_rate'] = (sum(_rate_hit(rate, r) for r in by[c]) / len(by[c])) if by[c] else None
        for key, field_, *_ in MEASURES:
            vals = np.array([r[field_] for r in by[c] if r[field_] is not None], dtype=float)
            entry[key] = {'mean': float(np.mean(vals)) if vals.size else None,
                          'median': float(np.median(vals)) if vals.size else None, 'n': int(vals.size)}
        per[c] = entry
    tests: dict[str, dict[str, Any]] = {}
    present = [c for c in conditions if by[c]]
    for i, a in enumerate(present):
        for b in present[i + 1:]:
            pair: dict[str, Any] = {'conditions': [a, b]}
            for key, field_, *_ in MEASURES:
                means = {}
                for c in (a, b):
                    per_pid: dict[str, list[float]] = {}
                    for r in by[c]:
                        if r[field_] is not None:
                            per_pid.setdefault(r['pid'], []).append(float(r[field_]))
                    means[c] = {pid: float(np.mean(v)) for pid, v in per_pid.items()}
                pids = sorted(set(means[a]) & set(means[b]))
                pair[key] = wilcoxon_test(np.array([means[a][p] for p in pids]), np.array([means[b][p] for p in pids]))
            for rate, *_ in RATES:
                index = {(r['pid'], r['trial'], r['condition']): _rate_hit(rate, r) for r in by[a] + by[b]}
                pairs = [(index[(pid, t, a)], index[(pid, t, b)]) for (pid, t, c) in index
                         if c == a and (pid, t, b) in index]
                pair[rate] = mcnemar_test(pairs)
                pair[rate]['unpaired'] = len(index) - 2 * len(pairs)
            tests[f'{a} vs {b}'] = pair
    return {'conditions': list(conditions), 'per_condition': per, 'tests': tests}


# ----------------------------------------------------------------------------------------- analysis
def analyze(parts: list[Participant]) -> dict[str, Any]:
    """Every figure of the paper's study analysis (unassisted vs assisted) and the per-landing measures of every
    condition of the study as summary.json's dictionary."""
    conditions = parts[0].conditions if parts else CONDITIONS
    rows_all = [r for p in parts for r in p.rows]
    excluded = {c: sum(1 for r in rows_all if r['condition'] == c and r['started_on_pad']) for c in CONDITIONS}
    kept = [r for r in rows_all if not r['started_on_pad']]
    rows = [r for r in kept if r['condition'] in CONDITIONS]           # the paper's figures: its two conditions
    by = {c: [r for r in rows if r['condition'] == c] for c in CONDITIONS}
    table: dict[str, dict[str, dict[str, float | None]]] = {}
    nearest_ok = {'success', 'wrong_pad'}
    for kind in ('specified', 'nearest'):
        stats = {}
        for c in CONDITIONS:
            err = np.array([r['error_m' if kind == 'specified' else 'nearest_error_m'] for r in by[c]], dtype=float)
            ok = np.array([r['success'] if kind == 'specified' else r['outcome'] in nearest_ok for r in by[c]],
                          dtype=bool)
            stats[c] = describe(err, ok)
        table[kind] = {m: {c: stats[c][m] for c in CONDITIONS} for m in stats[CONDITIONS[0]]}
    tests: dict[str, dict[str, Any]] = {}
    tests_nearest: dict[str, dict[str, Any]] = {}
    for kind, dest in (('specified', tests), ('nearest', tests_nearest)):
        key = 'error_m' if kind == 'specified' else 'nearest_error_m'
        succ = (lambda r: r['success']) if kind == 'specified' else (lambda r: r['outcome'] in nearest_ok)
        index = {(r['pid'], r['trial'], r['condition']): succ(r) for r in rows}
        pairs = [(index[(pid, t, 'unassisted')], index[(pid, t, 'assisted')])
                 for (pid, t, c) in index if c == 'unassisted' and (pid, t, 'assisted') in index]
        dest['mcnemar'] = mcnemar_test(pairs)
        dest['mcnemar']['unpaired'] = len(index) - 2 * len(pairs)      # the other condition's landing is missing
        dest.update(two_sample_tests(np.array([r[key] for r in by['unassisted']], dtype=float),
                                     np.array([r[key] for r in by['assisted']], dtype=float)))
    ratings = experience_ratings(parts)
    experienced, threshold = experienced_set(ratings)
    reg = regression(rows, experienced, conditions)
    levels, how = experience_levels(parts, ratings)
    per_participant = {}
    for p in parts:
        entry: dict[str, Any] = {'experience_level': levels.get(p.pid), 'experienced': p.pid in experienced}
        for c in conditions:
            errs = [r['error_m'] for r in p.rows if r['condition'] == c and not r['started_on_pad']]
            entry[f'median_error_m_{c}'] = float(np.median(errs)) if errs else None
            entry[f'landings_{c}'] = len(errs)
        entry['sus'] = p.sus
        per_participant[p.pid] = entry
    fig8 = {}
    for c in CONDITIONS:
        pts = [(v['experience_level'], v[f'median_error_m_{c}']) for v in per_participant.values()
               if v['experience_level'] is not None and v[f'median_error_m_{c}'] is not None]
        x, y = (np.array([a for a, _ in pts]), np.array([b for _, b in pts])) if pts else (np.zeros(0), np.zeros(0))
        fig8[c] = line_fit(x, y)
    sus = {}
    for c in conditions:
        scores = [p.sus[c] for p in parts if c in p.sus]
        mean = float(np.mean(scores)) if scores else None
        sus[c] = {'mean': mean, 'percentile': None if mean is None else sus_percentile(mean), 'n': len(scores)}
    assisted = by['assisted']
    inferred = [r for r in assisted if r['nearest_index'] is not None and r['nearest_index'] == r['goal_index']]
    goal_inference = {'rate': len(inferred) / len(assisted) if assisted else None,
                      'success_given_inferred': (sum(r['success'] for r in inferred) / len(inferred)
                                                 if inferred else None),
                      'landings': len(assisted)}
    return {'participants': len(parts), 'landings': {c: len(by[c]) for c in CONDITIONS}, 'excluded': excluded,
            'table': table, 'tests': tests, 'tests_nearest': tests_nearest, 'alpha': ALPHA,
            'regression': reg, 'experienced': {'threshold_mean_rating': threshold, 'n': len(experienced),
                                               'participants': sorted(experienced)},
            'experience_level': {'method': how, 'fits': fig8}, 'sus': sus, 'goal_inference': goal_inference,
            'per_participant': per_participant,
            'measures': dict(measures(kept, conditions),
                             excluded={c: sum(1 for r in rows_all if r['condition'] == c and r['started_on_pad'])
                                       for c in conditions})}


# ----------------------------------------------------------------------------------------- tables
def _fmt(metric: str, v: float | None) -> str:
    if v is None:
        return '-'
    if metric == 'success_rate':
        return f'{100 * v:.2f}%'
    return f'{v:.2f}m' if metric != 'variance_m2' else f'{v:.2f}m^2'


TEST_OF = {'success_rate': 'mcnemar', 'median_error_m': 'mood_median', 'mean_error_m': 't', 'variance_m2': 'f'}
ROW_NAMES = {'success_rate': 'Success rate', 'median_error_m': 'Median error', 'mean_error_m': 'Mean error',
             'variance_m2': 'Variance'}


def table_rows(summary: dict[str, Any]) -> list[list[str]]:
    """Table I as rows of cells (* marks the more favourable value where the test's p < alpha)."""
    out = []
    for metric, name in ROW_NAMES.items():
        cells = [name]
        for kind, tests in (('specified', summary['tests']), ('nearest', summary['tests_nearest'])):
            vals = summary['table'][kind][metric]
            p = tests[TEST_OF[metric]].get('p')
            best = None
            if p is not None and p < ALPHA and None not in vals.values():
                better = max if metric == 'success_rate' else min
                best = better(CONDITIONS, key=lambda c: vals[c])
            for c in CONDITIONS:
                cells.append(_fmt(metric, vals[c]) + ('*' if c == best else ''))
        out.append(cells)
    return out


def render_tables(summary: dict[str, Any]) -> tuple[str, str]:
    """(plain text, Markdown) of Table I plus the tests, regression, SUS and goal inference, then the per-landing
    measures per condition and their paired tests."""
    head = ['', 'Specified: unassisted', 'Specified: assisted', 'Nearest: unassisted', 'Nearest: assisted']
    rows = table_rows(summary)
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    m = summary.get('measures') or {}
    others = [c for c in m.get('conditions', ()) if c not in CONDITIONS]
    text = [f"User study: {summary['participants']} participants, {summary['landings']['unassisted']} unassisted and "
            f"{summary['landings']['assisted']} assisted landings (excluded: {summary['excluded']['unassisted']} "
            f"unassisted, {summary['excluded']['assisted']} assisted, ended on the starting platform)"
            + ''.join(f"; {m['per_condition'][c]['landings']} {c} landings ({m['excluded'][c]} excluded)"
                      for c in others)]
    text += validation_lines(summary.get('validation'))
    md = text + ['', '| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    text += ['  '.join(c.ljust(w) for c, w in zip(r, widths)) for r in [head] + rows]
    md += ['| ' + ' | '.join(r) + ' |' for r in rows]
    notes = ['* significantly more favourable (p < 0.01)']
    for name, key in (('McNemar (success)', 'mcnemar'), ("Mood's median test", 'mood_median'),
                      ("Welch's t-test", 't'), ('F-test (variance)', 'f')):
        t = summary['tests'][key]
        notes.append(f'{name}: statistic {_num(t["statistic"])}, p {_num(t["p"], 4)}'
                     + (f" ({t['pairs']} pairs; {t['unpaired']} landings without their pair)" if key == 'mcnemar'
                        else ''))
    reg = summary['regression']
    notes.append('Regression of error (m): ' + ', '.join(
        f"{k} {_num(reg[k]['coef'])} (p {_num(reg[k]['p'], 4)})" for k in ('assisted', 'first_half', 'experienced')))
    fits = summary['experience_level']['fits']
    notes.append('Median error vs experience level, slope: ' + ', '.join(
        f"{c} {_num(fits[c]['slope'])}" for c in CONDITIONS))
    sus = summary['sus']
    notes.append('SUS: ' + ', '.join(f"{c} {_num(sus[c]['mean'])} ({_ordinal(sus[c]['percentile'])} percentile)"
                                     for c in sus))
    gi = summary['goal_inference']
    notes.append(f"Goal inferred (assisted landings ended nearest the goal pad): {_pct(gi['rate'])}; of those "
                 f"successful: {_pct(gi['success_given_inferred'])}")
    text_m, md_m = render_measures(m) if m else ([], [])
    return ('\n'.join(text + [''] + notes + text_m) + '\n',
            '\n'.join(md + [''] + [f'- {n}' for n in notes] + md_m) + '\n')


MEASURES_TITLE = ('Per-landing measures by condition (landings not ended on the starting platform; time to land, '
                  'path length and key presses: mean / median per landing)')
TESTS_TITLE = ('Paired tests (* p < 0.01): Wilcoxon signed-rank on per-participant means (W, p, participants); '
               'McNemar on landings paired by participant and trial (statistic, p, pairs)')


def measure_rows(m: dict[str, Any]) -> list[list[str]]:
    """The measures table as rows of cells: a row per measure, a column per condition."""
    per = m['per_condition']
    conds = m['conditions']
    out = [['Landings'] + [str(per[c]['landings']) for c in conds]]
    for rate, label, _ in RATES:
        out.append([label] + [_pct(per[c][f'{rate}_rate']).replace(' ', '') for c in conds])
    for key, _, label, _ in MEASURES:
        out.append([label] + [f"{_num(per[c][key]['mean'])} / {_num(per[c][key]['median'])}" for c in conds])
    return out


def _test_text(t: dict[str, Any]) -> str:
    star = '*' if t.get('p') is not None and t['p'] < ALPHA else ''
    return f"{_num(t['statistic'])}, p {_num(t['p'], 4)}{star} ({t['pairs']})"


def render_measures(m: dict[str, Any]) -> tuple[list[str], list[str]]:
    """(plain text lines, Markdown lines) of the per-landing measures table and its paired tests."""
    head = [''] + list(m['conditions'])
    rows = measure_rows(m)
    widths = [max(len(r[i]) for r in [head] + rows) for i in range(len(head))]
    lines = []
    for name, t in m['tests'].items():
        parts = [f'{name} W {_test_text(t[key])}' for key, _, _, name in MEASURES]
        parts += [f'{name} McNemar {_test_text(t[rate])}' for rate, _, name in RATES]
        lines.append(f'{name}: ' + '; '.join(parts))
    if not lines:
        lines = ['no two conditions with landings to compare']
    text = ['', MEASURES_TITLE] + ['  '.join(c.ljust(w) for c, w in zip(r, widths)) for r in [head] + rows]
    text += [TESTS_TITLE] + lines
    md = ['', MEASURES_TITLE, '', '| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    md += ['| ' + ' | '.join(r) + ' |' for r in rows]
    md += ['', TESTS_TITLE, ''] + [f'- {line}' for line in lines]
    return text, md


def validation_lines(validation: dict[str, Any] | None) -> list[str]:
    """The tables' lines saying what was left out as invalid (nothing when nothing was)."""
    if not validation:
        return []
    out = []
    if validation['rows_excluded_total']:
        out.append(f"Left out as invalid: {validation['rows_excluded_total']} rows (" + ', '.join(
            f'{n} {reason}' for reason, n in validation['rows_excluded'].items()) + ')')
    out += [f'Left out: {line}' for line in validation['participants_excluded'] + validation['files_excluded']]
    return out


def _num(v: float | None, digits: int = 2) -> str:
    return '-' if v is None else f'{v:.{digits}f}'


def _ordinal(v: float | None) -> str:
    """31 -> '31st', 22 -> '22nd', 13 -> '13th' (rounded); '-' for None."""
    if v is None:
        return '-'
    n = int(round(v))
    suffix = 'th' if 10 <= n % 100 <= 20 else {1: 'st', 2: 'nd', 3: 'rd'}.get(n % 10, 'th')
    return f'{n}{suffix}'


def _pct(v: float | None) -> str:
    return '-' if v is None else f'{100 * v:.2f} %'


# ----------------------------------------------------------------------------------------- figures
def _save(fig: Any, path: Path, dpi: int = 120) -> None:
    """Write a figure as the new PNG file `path` (write_new) and free it."""
    import matplotlib.pyplot as plt
    fig.tight_layout()
    buf = io.BytesIO()
    try:
        fig.savefig(buf, dpi=dpi, format='png')
    finally:
        plt.close(fig)
    write_new(path, buf.getvalue())


def plot_violin(parts: list[Participant], path: Path) -> None:
    """Fig. 6: the distribution of landing errors per condition (every condition of the study)."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    conditions = parts[0].conditions if parts else CONDITIONS
    data = [[r['error_m'] for p in parts for r in p.rows if r['condition'] == c and not r['started_on_pad']]
            for c in conditions]
    fig, ax = plt.subplots(figsize=(5, 4))
    shown = [(c, d) for c, d in zip(conditions, data) if len(d) > 1]
    if shown:
        parts_ = ax.violinplot([d for _, d in shown], showmedians=True)
        for body, (c, _) in zip(parts_['bodies'], shown):
            body.set_facecolor(COLORS[c])
            body.set_alpha(0.6)
        ax.set_xticks(range(1, len(shown) + 1), [c for c, _ in shown])
    ax.set_ylabel('error to the goal pad centre (m)')
    ax.set_title('Landing error per condition')
    _save(fig, path)


def plot_experience(summary: dict[str, Any], path: Path) -> None:
    """Fig. 8: per-participant median error against experience level, a fitted line per condition."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(5, 4))
    for c in CONDITIONS:
        pts = [(v['experience_level'], v[f'median_error_m_{c}']) for v in summary['per_participant'].values()
               if v['experience_level'] is not None and v[f'median_error_m_{c}'] is not None]
        if not pts:
            continue
        x, y = np.array(pts).T
        ax.scatter(x, y, color=COLORS[c], label=c)
        fit = summary['experience_level']['fits'][c]
        if fit['slope'] is not None:
            xs = np.linspace(0, 1, 2)
            ax.plot(xs, fit['intercept'] + fit['slope'] * xs, color=COLORS[c],
                    label=f"{c} fit (slope {fit['slope']:.2f})")
    ax.set_xlabel('experience level (0 novice, 1 expert)')
    ax.set_ylabel('median error (m)')
    ax.legend(fontsize=8)
    _save(fig, path)


def bag_track(bag: Path) -> tuple[np.ndarray, np.ndarray | None]:
    """(N x 3 /odom positions from the episode's start, pad boxes as rows of cx, cy, sx, sy, yaw, or None) of a
    landing's bag."""
    from assist_bags.bagio import BagReader
    pts, pads = [], None
    with BagReader(bag) as reader:
        topics = [t for t in ('/odom', '/sim/scene') if t in reader.select(None)]
        for conn_topic, _t, raw in reader.messages(topics):
            msg = reader.deserialize(raw, conn_topic)
            if conn_topic == '/odom':
                p = msg.pose.pose.position
                pts.append((p.x, p.y, p.z))
            else:
                boxes = []
                for m in msg.markers:
                    if m.ns == 'platforms' and m.action == 0:
                        q = m.pose.orientation
                        yaw = heading((q.x, q.y, q.z, q.w))
                        boxes.append((m.pose.position.x, m.pose.position.y, m.scale.x, m.scale.y, yaw))
                if boxes:
                    pads = np.array(boxes)
    track = np.array(pts).reshape(-1, 3)
    if len(track) > 1:      # the bag opens before /sim/reset: keep the flight after the last teleport
        jumps = np.flatnonzero(np.linalg.norm(np.diff(track, axis=0), axis=1) > JUMP_M)
        if jumps.size:
            track = track[jumps[-1] + 1:]
    return track, pads


def plot_trajectories(parts: list[Participant], n: int, path: Path) -> int:
    """Fig. 7: top views of chosen landings (one trial flown unassisted and assisted, and with cues where the study
    has them) from their bags; returns panels drawn."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib.patches import Polygon
    chosen = []
    for p in parts:
        if len(chosen) >= n:
            break
        trials = {}
        for r in p.rows:
            if r['bag'] and (p.dir / 'bags' / r['bag']).is_dir():
                trials.setdefault(r['trial'], {})[r['condition']] = r
        both = sorted(t for t, d in trials.items() if all(c in d for c in CONDITIONS))
        if both:
            chosen.append((p, trials[both[len(both) // 2]]))
    if not chosen:
        return 0
    fig, axes = plt.subplots(len(chosen), 1, figsize=(10, 2.6 * len(chosen)), squeeze=False)   # long scenes: rows
    drawn = 0
    for ax, (p, pair) in zip(axes[:, 0], chosen):
        for c in [c for c in p.conditions if c in pair]:
            r = pair[c]
            try:
                track, pads = bag_track(p.dir / 'bags' / r['bag'])
            except Exception as exc:  # noqa: BLE001 - a damaged bag costs its panel line, not the analysis
                log.warning('%s: bag %s unreadable (%s); not drawn', p.pid, r['bag'], exc)
                continue
            if pads is not None and c == CONDITIONS[0]:
                for k, (cx, cy, sx, sy, yaw) in enumerate(pads):
                    corners = [np.array([cx, cy]) + rotate_xy((dx, dy), yaw)
                               for dx, dy in ((-sx / 2, -sy / 2), (sx / 2, -sy / 2), (sx / 2, sy / 2),
                                              (-sx / 2, sy / 2))]
                    ax.add_patch(Polygon(corners, closed=True, fill=k == r['goal_index'], alpha=0.35,
                                         color='orange' if k == r['goal_index'] else 'gray'))
            if len(track):
                ax.plot(track[:, 0], track[:, 1], color=COLORS[c], label=f"{c}: {r['outcome']}")
                ax.plot(track[-1, 0], track[-1, 1], 'o', color=COLORS[c])
                drawn += 1
        ax.set_title(f"{p.pid}, trial {pair[CONDITIONS[0]]['trial'] + 1}")
        ax.set_aspect('equal')
        ax.set_xlabel('x (m)')
        ax.set_ylabel('y (m)')
        ax.legend(fontsize=7)
    _save(fig, path)
    return drawn


# ----------------------------------------------------------------------------------------- main
def check_outputs(out: Path) -> None:
    """StudyError unless none of the outputs stands in `out` (a file, a directory or a symbolic link, even one
    that points nowhere: writing through it would land outside `out`)."""
    taken = [name for name in OUTPUTS if os.path.lexists(out / name)]
    if taken:
        raise StudyError(f'{out}: {", ".join(taken)} exist already; not overwriting (use another --out)')
    if os.path.lexists(out) and not out.is_dir():
        raise StudyError(f'{out}: not a directory')


def write_new(path: Path, data: bytes) -> None:
    """Write `data` as the new file `path` (crash-safe: a hidden temporary, fsynced, then published under the
    name only where nothing stands, not even a dangling link; never follows or replaces one). StudyError when
    something is there, OSError when the disk refuses."""
    from assist_bags.bagio import BagError, publish_new
    tmp = path.with_name(f'.{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp')
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, 'O_NOFOLLOW', 0), 0o666)   # umask applies
    try:
        with os.fdopen(fd, 'wb') as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    try:
        publish_new(Path(tmp), path)
    except BagError as exc:
        raise StudyError(str(exc)) from None
    fsync_dir(path.parent)


def strict_json(value: Any) -> Any:
    """`value` with every non-finite float (a statistic that is not defined on these data) as None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [strict_json(v) for v in value]
    return value


def run(dirs: list[Path], args: AnalyzeArgs) -> dict[str, Any]:
    """Analyse the participant directories into args.out; returns the summary. StudyError when nothing can be
    analysed or an output exists already (nothing is written then)."""
    out = Path(args.out)
    check_outputs(out)
    val = Validation()
    parts = load_study(dirs, args, val)
    if not parts:
        why = '; '.join(val.participants) or 'no participant directory among the arguments'
        raise StudyError(f'nothing to analyse: {why}')
    summary = analyze(parts)
    summary['validation'] = val.as_dict()
    summary = strict_json(summary)
    text, md = render_tables(summary)
    out.mkdir(parents=True, exist_ok=True)
    write_new(out / 'table.txt', text.encode('utf-8'))
    write_new(out / 'table.md', md.encode('utf-8'))
    if args.plots:
        plot_violin(parts, out / 'violin.png')
        plot_experience(summary, out / 'experience.png')
        if args.trajectories:
            summary['trajectory_panels'] = plot_trajectories(parts, args.trajectories, out / 'trajectories.png')
    write_new(out / 'summary.json', (json.dumps(summary, indent=1, allow_nan=False) + '\n').encode('utf-8'))
    return summary


def main(argv: list[str] | None = None) -> int:
    """Console entry point: analyse, print the table."""
    cmd = parse_command(AnalyzeArgs, 'analyze_study', __doc__, HELP, argv,
                        positional={'dirs': dict(nargs='+', type=Path,
                                                 help='participant directories (e.g. study_data/*)')})
    args = cmd.settings
    try:
        summary = run(cmd.namespace.dirs, args)
    except (StudyError, OSError) as exc:
        print(f'error: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}', file=sys.stderr)
        return 1
    text, _ = render_tables(summary)
    print(text, end='')
    print(f'written to {args.out}/ (summary.json, table.txt, table.md' + (', figures)' if args.plots else ')'))
    return 0


if __name__ == '__main__':
    sys.exit(main())
