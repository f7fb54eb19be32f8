"""The station's study driver (study_station.StudyDriver) on an rclpy node in this process, with no graph around
it (its timer not spun: each test calls tick): page steps under a full disk, a landing saved whose log line
is not, bursts of steps from a page."""
import errno
import os
import random

import pytest
import rclpy
from rclpy.context import Context
from rclpy.node import Node

from assist_station.station_core import StudyMessage
from assist_station.study import SURVEY, StudyConfig, StudySession
from assist_station.study_station import INBOX_SIZE, StudyDriver

TEXT = 'sequence: [1, 3]\npractice_landings: 1\nrecord_bags: false\n'
CFG = StudyConfig.from_text(TEXT)


class Logger:
    """Stands in for the node's logger: keeps every line by level."""

    def __init__(self):
        self.lines = {'debug': [], 'info': [], 'warning': [], 'error': []}

    def __getattr__(self, level):
        return lambda text, **_: self.lines[level].append(text)


class Harness:
    """A StudyDriver whose views, page events and log lines are recorded."""

    def __init__(self, node, root):
        self.views, self.events, self.log = [], [], Logger()
        node.get_logger = lambda: self.log
        self.driver = StudyDriver(node, CFG, TEXT, root, self.views.append, self.events.append)

    def send(self, action, **data):
        self.driver.submit(StudyMessage(action, data))

    def step(self, action, **data):
        self.send(action, **data)
        self.driver.tick()

    def errors(self):
        return [e['message'] for e in self.events if e['type'] == 'study_error']


@pytest.fixture
def node():
    ctx = Context()
    rclpy.init(context=ctx, domain_id=random.randint(80, 89))
    n = Node('study_driver_test', context=ctx)
    try:
        yield n
    finally:
        n.destroy_node()
        rclpy.shutdown(context=ctx)


@pytest.fixture
def h(node, tmp_path):
    harness = Harness(node, tmp_path)
    yield harness
    harness.driver.close()


def no_space(fd):
    raise OSError(errno.ENOSPC, 'No space left on device')


def test_a_full_disk_at_start_landing_is_reported_and_a_retry_starts_the_landing(h, tmp_path, monkeypatch):
    h.step('begin', participant='P01')
    h.step('consent')
    log = tmp_path / 'P01' / 'protocol.log'
    before = log.read_bytes()
    monkeypatch.setattr(os, 'fsync', no_space)
    h.step('start')
    monkeypatch.undo()
    assert 'could not save (No space left on device)' in h.errors()[-1]
    assert h.driver.stage == 'idle' and h.driver.session.active is None
    assert h.views[-1]['in_flight'] is False and 'No space left' in h.views[-1]['error']
    assert log.read_bytes() == before                     # nothing half written, nothing lost
    n_errors = len(h.errors())
    h.step('start')                                       # space is back: the retry starts the landing
    assert len(h.errors()) == n_errors
    assert h.driver.session.active is not None and h.driver.stage != 'idle'
    assert h.views[-1]['in_flight'] is True and 'error' not in h.views[-1]


def test_a_saved_landing_whose_log_line_fails_is_reported_recorded(h, tmp_path, monkeypatch):
    h.step('begin', participant='P01')
    h.step('consent')
    h.step('start')
    spec = h.driver.session.active
    h.driver.stage, h.driver.episode = 'flying', 5          # what /sim/reset's answer would have set
    store = h.driver.session.store
    real_log = store.log

    def log(event, **data):
        if event in ('landing_recorded', 'practice_done'):
            raise OSError(errno.ENOSPC, 'No space left on device')
        real_log(event, **data)
    monkeypatch.setattr(store, 'log', log)
    result = {'episode': 5, 'goal_index': spec.goal_index, 'landed_index': spec.goal_index, 'nearest_index': 0,
              'error_m': 0.1, 'nearest_error_m': 0.1, 'success': True, 'crash': False, 'outcome': 'success',
              'duration_s': 9.0, 'assisted': False}
    assert h.driver.on_landing(result) is True
    assert not any('not recorded' in e for e in h.errors())
    assert any(e.startswith('saved, but protocol.log event landing_recorded not written') for e in h.errors())
    assert any('landing_recorded not written' in line for line in h.log.lines['error'])
    assert h.driver.stage == 'closing' and h.driver.session.phase == 'block1'
    assert (tmp_path / 'P01' / 'landings.csv').read_text().count('\n') == 2       # header and the row


def test_a_begin_burst_opens_one_participant_and_logs_a_few_lines(h, tmp_path):
    h.driver._warnings.period_s = 3600.0                    # this whole test falls in one warning period
    for i in range(74):
        h.send('begin', participant=f'S{i + 1:02d}')
        h.send('begin', participant='S01')
    h.driver.tick()
    assert sorted(p.name for p in tmp_path.iterdir()) == ['S01'] and h.driver.session.pid == 'S01'
    assert h.errors() == ['a participant is being opened already; more begin steps are refused until it is']
    assert len(h.log.lines['warning']) == 1 and '147 duplicate' in h.log.lines['info'][-1]
    for _ in range(3):                                     # more bursts while S01 is open: refused, nothing made
        for i in range(74):
            h.send('begin', participant=f'X{i:02d}')
        h.driver.tick()
    assert sorted(p.name for p in tmp_path.iterdir()) == ['S01']
    assert len(h.errors()) == 1 + 3 * 2                    # per burst: the duplicates once, the begin handled once
    assert 'S01 has not finished' in h.errors()[-1]
    assert len(h.log.lines['warning']) == 2                # each kind of refusal once per period
    assert len((tmp_path / 'S01' / 'protocol.log').read_text().splitlines()) == 1


def test_a_step_burst_beyond_the_inbox_is_dropped_with_one_line(h):
    h.driver._warnings.period_s = 3600.0
    h.step('begin', participant='P01')
    for _ in range(INBOX_SIZE + 36):
        h.send('consent')
    h.driver.tick()
    assert h.driver.session.phase == 'practice'
    assert h.errors().count('consent was given already') == INBOX_SIZE - 1
    assert len(h.log.lines['warning']) == 2                 # 36 dropped: one line; 63 refused: one line


def test_the_next_participant_begins_once_the_open_one_is_done(h, tmp_path):
    s = StudySession(CFG, TEXT, tmp_path, 'P01')            # P01 went through the whole protocol
    s.consent()
    for _ in range(5):
        spec = s.start_landing()
        s.record_landing({'episode': 1, 'goal_index': spec.goal_index, 'success': True}, start_pad=None, episode=1,
                         bag=None)
        if s.phase in ('sus1', 'sus2'):
            s.submit_sus([3] * 10)
    s.submit_survey({str(q['id']): ([] if q['kind'] == 'multi' else 1) for q in SURVEY})
    h.step('begin', participant='P02')
    h.step('begin', participant='P03')                      # P02 has not finished: refused, no directory
    assert 'P02 has not finished (at consent)' in h.errors()[-1] and not (tmp_path / 'P03').exists()
    h.step('consent')
    assert h.driver.session.pid == 'P02' and h.driver.session.phase == 'practice'
    h2 = Harness(h.driver.node, tmp_path)                   # a station with P01 open, then P02 after it
    h2.step('begin', participant='P01')
    assert h2.views[-1]['phase'] == 'done'
    h2.step('begin', participant='P04')
    assert h2.driver.session.pid == 'P04' and h2.errors() == []
    h2.driver.close()


class Future:
    """A service call's future, answered when the test says."""

    def __init__(self, answer=None):
        self.answer = answer

    def done(self):
        return self.answer is not None

    def result(self):
        return self.answer


def test_calls_not_answered_in_time_are_sent_again_then_fail_the_step_once(h, monkeypatch):
    from assist_station import study_station
    now = [1000.0]
    monkeypatch.setattr(study_station.time, 'monotonic', lambda: now[0])
    answered, sent = [], []

    def again():
        sent.append(Future())
        return sent[-1]
    call = study_station._Call('setting policy_node parameters', Future(), answered.append, again=again)
    h.driver._calls.append(call)
    now[0] += study_station.SERVICE_WAIT_S + 0.1
    h.driver.tick()                                  # not answered in time: sent again, nothing failed
    assert len(sent) == 1 and call.tries == 2 and h.driver._calls == [call] and not h.errors()
    sent[-1].answer = 'ok'
    h.driver.tick()                                  # the second request's answer is taken
    assert answered == ['ok'] and not h.driver._calls and not h.errors()
    # a node whose queue runs longer than the wait answers the first request after the second was sent: taken
    first_try = Future()
    late = study_station._Call('setting policy_node parameters', first_try, answered.append, again=again)
    h.driver._calls.append(late)
    now[0] += study_station.SERVICE_WAIT_S + 0.1
    h.driver.tick()
    assert len(sent) == 2 and late.tries == 2 and h.driver._calls == [late]
    first_try.answer = 'late'
    h.driver.tick()
    assert answered == ['ok', 'late'] and not h.driver._calls and not h.errors()
    # two calls out of time and out of tries: the first fails the step and drops the second, which is not
    # touched again (it used to raise from the tick: list.remove of a call already dropped)
    first = study_station._Call('setting policy_node parameters', Future(), answered.append)
    second = study_station._Call('reading encoder_node parameters', Future(), answered.append)
    h.driver._calls += [first, second]
    now[0] += study_station.SERVICE_WAIT_S + 0.1
    h.driver.tick()
    assert h.errors() == ['setting policy_node parameters: no answer within 10 s (1 tries)']
    assert not h.driver._calls and answered == ['ok', 'late']
