"""A simulated participant that uses the station page in headless Chromium (its forms, buttons and key handling).

The same participant as assist_station.participant (pilot family, skill, scripted answers), but every step
goes through the page: the participant ID is typed into the page's field, consent, start, finish-practice
and submit are clicks on the page's buttons, questionnaire answers are clicks on its radio buttons and
check boxes, and the flight keys are keyboard events dispatched to the page, which sends them to the
station exactly as it does for a person. The pose, the goal and (in an assisted_cues landing) the intent cues
the page draws come from the page's own state (window.stationStats).
"""
from __future__ import annotations

import logging
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from .participant import (FLIGHT_START_TIMEOUT_S, STEP_TIMEOUT_S, Flyer, ParticipantError, Profile, cue_shown, felt,
                          step_key, sus_answers, survey_answers)
from .study import CUE_CONDITION, phase_block
from .testing import start_browser

log = logging.getLogger(__name__)
PILOT_WAIT_S = 60.0
#: [[name, value], ...] -> the answers whose input is missing, disabled or not displayed.
ANSWERS_SHOWN_JS = """
return arguments[0].filter(([name, value]) => {
  const e = document.querySelector(`input[name="${name}"][value="${value}"]`);
  return !e || e.disabled || e.offsetParent === null;
}).map(([name, value]) => `${name}=${value}`);
"""
#: [[name, value], ...]: click each answer's input (a person's click: the input's own events), then return the
#: answers not checked afterwards.
ANSWERS_CLICK_JS = """
const find = ([name, value]) => document.querySelector(`input[name="${name}"][value="${value}"]`);
for (const answer of arguments[0]) { const e = find(answer); if (e && !e.checked) e.click(); }
return arguments[0].filter((answer) => { const e = find(answer); return !e || !e.checked; })
                   .map(([name, value]) => `${name}=${value}`);
"""
POLL_S = 0.05             # s between checks of the page while waiting for a form's answer (selenium's default: 0.5 s)

# one round trip per pilot step: set the held keys by dispatching key events, return what the page knows
STEP_JS = """
const want = arguments[0];
const held = window.__simHeld || [];
for (const k of held) if (!want.includes(k)) window.dispatchEvent(new KeyboardEvent('keyup', {code: k, key: k}));
for (const k of want) if (!held.includes(k)) window.dispatchEvent(new KeyboardEvent('keydown', {code: k, key: k}));
window.__simHeld = want.slice();
const s = window.stationStats;
return {study: s.study || null, pose: s.pose, scene: s.scene || null, ws: s.ws, role: s.role,
        speed: s.speed, speedZ: s.speedZ, errors: s.studyErrors || 0, cues: s.cues || null};
"""


class BrowserParticipant:
    """Drives one simulated participant through the station page in headless Chromium."""

    def __init__(self, url: str, profile: Profile, real_time_factor: float, work_dir: Path,
                 reload_during: tuple[str, int] | None = None, on_landing=None):
        self.url, self.profile, self.rtf = url, profile, float(real_time_factor)
        self.reload_during = reload_during      # (phase, trial): reload the page once in that landing's flight
        self.on_landing = on_landing or (lambda: None)      # called after each landing flown (progress)
        self.work = Path(work_dir)
        self.rng = np.random.default_rng(profile.seed)
        self.outcomes: dict[str, list[float]] = {'unassisted': [], 'assisted': []}
        self.cue_steps: dict[str, list[int]] = {}     # condition -> [pilot steps flown, steps with a cue drawn]
        self.landings_flown = 0
        self.reloads = 0
        self.driver = None

    def _stats(self, keys: list[str] | None = None) -> dict[str, Any]:
        return self.driver.execute_script(STEP_JS, [] if keys is None else keys)

    def _view(self) -> dict[str, Any] | None:
        return self._stats(getattr(self, '_held', []))['study']

    def _wait(self, cond, what: str, timeout_s: float = STEP_TIMEOUT_S) -> dict[str, Any]:
        end = time.monotonic() + timeout_s
        while True:
            st = self._stats(getattr(self, '_held', []))
            if cond(st):
                return st
            if time.monotonic() > end:
                raise ParticipantError(f'page did not show {what} within {timeout_s:.0f} s '
                                       f"(study view: {st['study']})")
            time.sleep(0.05)

    def _click(self, element_id: str, timeout_s: float = STEP_TIMEOUT_S) -> None:
        """Click a page element by id; the panel may be redrawn under the click (a newer view): find it again."""
        from selenium.common.exceptions import (ElementClickInterceptedException, NoSuchElementException,
                                                StaleElementReferenceException)
        from selenium.webdriver.common.by import By
        end = time.monotonic() + timeout_s
        while True:
            try:
                self.driver.find_element(By.ID, element_id).click()
                return
            except (StaleElementReferenceException, NoSuchElementException, ElementClickInterceptedException):
                if time.monotonic() > end:
                    raise
                time.sleep(0.1)

    def _act(self, element_id: str) -> None:
        """Click a study button and wait until the station's view moves on to another step (participant, phase,
        trial or a landing begun) or an error shows; a view of the same step (its stage changing, say) is not the
        result of the click."""
        before = step_key(self._view())
        errors = self._stats()['errors']
        self._click(element_id)
        st = self._wait(lambda s: step_key(s['study']) != before or s['errors'] > errors, f'the result of {element_id}')
        if st['errors'] > errors:
            text = self.driver.execute_script("const e = document.getElementById('study-error'); "
                                              "return e ? e.textContent : '';")
            raise ParticipantError(f'station refused {element_id}: {text}')

    def _answer_all(self, answers: list[tuple[str, int]]) -> None:
        """Answer a questionnaire on the page: once every answer's input shows (up to STEP_TIMEOUT_S), click each
        in one script run, as the page's own click handlers see a person's clicks, then check they all stuck.

        One round trip per form, not per answer: with the graph and the page busy on two cores, a WebDriver
        command took ~0.7 s, so a 21-question survey took 15 s answer by answer."""
        end = time.monotonic() + STEP_TIMEOUT_S
        while True:
            hidden = self.driver.execute_script(ANSWERS_SHOWN_JS, answers)
            if not hidden:
                break
            if time.monotonic() > end:
                shown = self.driver.execute_script(
                    "const p = document.getElementById('study'); return p ? p.innerText.slice(0, 200) : '';")
                raise ParticipantError(f'answers {hidden} not shown within {STEP_TIMEOUT_S:.0f} s '
                                       f'(study view: {self._view()}; the panel showed: {shown!r}; '
                                       f'console: {self.driver.get_log("browser")[-5:]})')
            time.sleep(POLL_S)
        unchecked = self.driver.execute_script(ANSWERS_CLICK_JS, answers)
        if unchecked:
            raise ParticipantError(f'answers {unchecked} not checked after clicking them')

    def run(self) -> dict[str, Any]:
        """Go through the whole protocol in the page; returns what happened (ParticipantError if it cannot)."""
        from selenium.common.exceptions import WebDriverException
        try:
            return self._run()
        except WebDriverException as exc:
            first = str(exc.msg or exc).splitlines()[0]
            shown = ''
            try:
                shown = self.driver.execute_script(
                    "const p = document.getElementById('study'); return p ? p.innerText.slice(0, 300) : '';")
                logs = self.driver.get_log('browser')[-5:]
            except WebDriverException:
                logs = []
            raise ParticipantError(f'{self.profile.pid} in the browser: {first} (the study panel showed: '
                                   f'{shown!r}; console: {logs})') from None
        finally:
            if self.driver is not None:
                self.driver.quit()

    def _run(self) -> dict[str, Any]:
        from selenium.webdriver.common.by import By
        self.work.mkdir(parents=True, exist_ok=True)
        self.driver = start_browser(self.work / 'chromium-profile')
        end = time.monotonic() + PILOT_WAIT_S
        while True:             # the pilot role waits for the previous pilot's page (pilot_grace_s): reload
            self.driver.get(self.url)
            st = self._wait(lambda s: s['role'] is not None and s['study'] is not None, 'the study', 30.0)
            if st['role'] == 'pilot':
                break
            if time.monotonic() > end:
                raise ParticipantError(f'the page stayed view only for {PILOT_WAIT_S:.0f} s')
            time.sleep(1.0)
        view = self._view()
        if view.get('participant') != self.profile.pid or view['phase'] == 'participant':
            self._wait(lambda s: s['study']['phase'] == 'participant' or s['study'].get('participant'),
                       'the participant prompt')
            if self._view()['phase'] == 'participant':
                self.driver.find_element(By.ID, 'study-id').send_keys(self.profile.pid)
                self._act('study-begin')
        while True:
            v = self._view()
            phase = v['phase']
            if phase == 'consent':
                self._act('study-consent')
            elif phase == 'practice' and v['trial'] > self.profile.practice:
                self._act('study-stop-practice')
            elif phase == 'practice' or (phase.startswith('block') and phase_block(phase)):
                self._fly(v)
            elif phase.startswith('sus') and phase_block(phase):
                self._answer_all([(f'sus-{i}', int(a)) for i, a in
                                  enumerate(sus_answers(self.rng, felt(self.outcomes.get(v['condition'], []))))])
                self._act('study-submit')
            elif phase == 'survey':
                answers = survey_answers(self.rng, self.profile, {c: felt(d) for c, d in self.outcomes.items()})
                self._answer_all([(f'q-{q}', int(value)) for q, a in answers.items()
                                  for value in (a if isinstance(a, list) else [a])])
                self._act('study-submit')
            elif phase == 'done':
                break
            else:
                raise ParticipantError(f'unexpected study phase {phase!r}')
        return {'participant': self.profile.pid, 'landings_flown': self.landings_flown, 'reconnects': self.reloads,
                'profile': asdict(self.profile), 'cue_steps': self.cue_steps}

    def _fly(self, v: dict) -> None:
        key = (v['phase'], v['trial'])

        def same(s: dict) -> bool:
            return s['study'] is not None and (s['study']['phase'], s['study'].get('trial')) == key

        st = self._wait(lambda s: not same(s) or not s['study'].get('in_flight'), 'the landing to be startable')
        if not same(st):                # e.g. a landing the station aborted and recorded meanwhile: look again
            return
        self._act('study-start')
        st = self._wait(lambda s: not same(s) or (s['study'].get('stage') == 'flying' and s['pose'] is not None
                                                   and s['scene'] is not None), 'the landing in flight',
                       FLIGHT_START_TIMEOUT_S)
        if not same(st):
            return
        flyer = Flyer(self.profile, self.landings_flown, st['scene'], np.array(st['pose']['p']),
                      float(st['speed'] or 1.0), float(st['speedZ'] or 0.5),
                      reads_cues=v.get('condition') == CUE_CONDITION)
        period = flyer.period_s / self.rtf
        self._held: list[str] = []
        next_t = started = time.monotonic()
        last_pose = st['pose']
        while same(st) and st['study'].get('stage') == 'flying':
            if self.reload_during == key and time.monotonic() - started > 1.0:
                self.reload_during = None       # a closed tab / reload mid-landing: the station flies it again
                self._held = []
                self.driver.get(self.url)
                self._wait(lambda s: s['role'] == 'pilot' and s['study'] is not None, 'the page back', 30.0)
                self.reloads += 1
                return
            if st['ws'] != 'open':
                raise ParticipantError('the page lost the station during a landing')
            last_pose = st['pose'] or last_pose
            seen = self.cue_steps.setdefault(v.get('condition', ''), [0, 0])
            seen[0] += 1
            seen[1] += cue_shown(st.get('cues'))
            self._held = list(flyer.step(last_pose, st.get('cues')))
            next_t += period
            time.sleep(max(0.0, next_t - time.monotonic()))
            if time.monotonic() - next_t > 1.0:
                next_t = time.monotonic()
            st = self._stats(self._held)
        self._held = []
        self._stats([])
        self.outcomes.setdefault(v.get('condition', 'unassisted'), []).append(flyer.distance(last_pose))
        self.landings_flown += 1
        self.on_landing()
