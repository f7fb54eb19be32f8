"""The station's study driver through a three-block study on stand-in nodes in this process (sim_node's parameters
and /sim/reset, policy_node's parameters; no simulator): the station's own cue switches per landing (on only in
assisted_cues landings, off from the start, between landings and in the other blocks), policy_node's
assist_enabled per block, and the measures each row gets (path flown from /odom, key presses and corrective ones
from the station's key state)."""
import csv
import time

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from assist_common.domains import private_domain_id
from assist_common.ros_params import declare_parameters
from assist_station.pilot_station import PARAMS
from assist_station.station_core import StationConfig, StudyMessage
from assist_station.study import SURVEY, StudyConfig
from assist_station.study_station import CUE_PARAMETERS, CountingKeyState, StudyDriver

TEXT = 'sequence: [1, 3]\npractice_landings: 1\nrecord_bags: false\nconditions: [unassisted, assisted, assisted_cues]\n'
CFG = StudyConfig.from_text(TEXT)
WAIT_S = 30.0
# a landing's /odom track as (position, stamp): a sample from before the reset, the reset's teleport, 3 m along x
# at 1 m/s, 2 m along y in one step (the station missed 2 s of samples), a late sample stamped before the last
# one, then a 1.2 m descent: 6.2 m flown
TRACK = ([((10.0, 10.0, 0.2), 100.0), ((0.0, 0.0, 2.0), 100.05)]
         + [((0.5 * i, 0.0, 2.0), 100.05 + 0.5 * i) for i in range(1, 7)]
         + [((3.0, 2.0, 2.0), 105.05), ((40.0, 40.0, 0.0), 104.0)]
         + [((3.0, 2.0, 2.0 - 0.3 * i), 105.05 + 0.3 * i) for i in range(1, 5)])
TRACK_M = 3.0 + 2.0 + 1.2


class Graph:
    """Stand-ins for the study's graph, the station node that hosts the driver and an executor spun by `until`."""

    def __init__(self, ctx, root):
        self.station = Node('pilot_station', context=ctx)
        self.p = declare_parameters(self.station, {k: PARAMS[k] for k in CUE_PARAMETERS})   # as the station: True
        self.sim = Node('sim_node', context=ctx)
        for name, value in (('scene_seed', 0), ('goal_index', 0), ('auto_reset', True)):
            self.sim.declare_parameter(name, value)
        self.episodes = 0
        self.land_before_answer = False      # /sim/reset: the episode's result reaches the station before the answer
        self.early: list[bool] = []          # what the driver said to each such result
        self.sim.create_service(Trigger, '/sim/reset', self._reset)
        self.policy = Node('policy_node', context=ctx)
        for name, value in (('assist_enabled', False), ('mode', 'latent'), ('model_path', '')):
            self.policy.declare_parameter(name, value)
        self.executor = SingleThreadedExecutor(context=ctx)
        for n in (self.station, self.sim, self.policy):
            self.executor.add_node(n)
        self.keys = CountingKeyState(StationConfig())
        self.views, self.events = [], []
        self.driver = StudyDriver(self.station, CFG, TEXT, root, self.views.append, self.events.append,
                                  key_counter=self.keys.counter)

    def _reset(self, request, response):
        self.episodes += 1
        response.success = True
        response.message = f"episode {self.episodes}: goal pad {self.sim.get_parameter('goal_index').value}"
        if self.land_before_answer:      # a short landing on a loaded machine: over before the answer is handled
            self.early.append(self.driver.on_landing(result(self.driver.spec, self.episodes)))
        return response

    def cues(self):
        return {n: self.station.get_parameter(n).value for n in CUE_PARAMETERS}

    def until(self, cond, what):
        end = time.monotonic() + WAIT_S
        while not cond():
            assert time.monotonic() < end, f'{what} not within {WAIT_S:.0f} s (errors: {self.errors()})'
            self.executor.spin_once(timeout_sec=0.02)
            self.driver.tick()

    def step(self, action, **data):
        self.driver.submit(StudyMessage(action, data))
        self.driver.tick()

    def errors(self):
        return [e['message'] for e in self.events if e['type'] == 'study_error']


@pytest.fixture
def graph(tmp_path):
    ctx = Context()
    rclpy.init(context=ctx, domain_id=private_domain_id())
    g = Graph(ctx, tmp_path)
    try:
        yield g
    finally:
        g.driver.close()
        g.executor.shutdown()
        for n in (g.station, g.sim, g.policy):
            n.destroy_node()
        rclpy.shutdown(context=ctx)


def result(spec, episode: int) -> dict:
    """sim_node's /sim/landing result of `episode`: a success on the spec's goal pad."""
    return {'episode': episode, 'goal_index': spec.goal_index, 'landed_index': spec.goal_index,
            'nearest_index': spec.goal_index, 'error_m': 0.1, 'nearest_error_m': 0.1, 'success': True,
            'crash': False, 'outcome': 'success', 'duration_s': 12.0, 'assisted': spec.assisted}


def fly_landing(g, keys):
    """Start the next landing, fly TRACK and `keys` (held sets in turn), land; returns (spec, cues while flying,
    assist_enabled while flying)."""
    g.step('start')
    g.until(lambda: g.driver.stage == 'flying', 'the landing in flight')
    spec = g.driver.spec
    cues, assisted = g.cues(), g.policy.get_parameter('assist_enabled').value
    for p, t in TRACK:
        g.driver.note_odom(p, t)
    now = time.monotonic()
    for held in keys:
        g.keys.set(held, now)
    assert g.driver.on_landing(result(spec, g.driver.episode)) is True
    return spec, cues, assisted


def test_cues_switch_per_landing_and_rows_carry_the_measures(graph, tmp_path):
    g = graph
    assert g.cues() == {n: False for n in CUE_PARAMETERS}        # off from the start (declared True)
    g.step('begin', participant='P03')                           # order: assisted_cues, unassisted, assisted
    g.step('consent')
    seen = []
    keys = [['KeyW'], [], ['KeyS'], ['KeyS', 'ArrowDown'], ['Space']]     # 4 presses: S after W, Space corrective
    while g.driver.session.phase != 'survey':
        phase = g.driver.session.phase
        if phase.startswith('sus'):
            g.step('sus', answers=[3] * 10)
            continue
        spec, cues, assisted = fly_landing(g, keys)
        seen.append((spec.name, spec.condition, cues, assisted))
        assert g.cues() == {n: False for n in CUE_PARAMETERS}    # off once the landing is recorded
        g.until(lambda: g.driver.stage == 'idle', 'the landing closed')
    assert g.errors() == []
    assert [s[:2] for s in seen] == [('practice_00', 'assisted_cues'),
                                     ('block1_00', 'assisted_cues'), ('block1_01', 'assisted_cues'),
                                     ('block2_00', 'unassisted'), ('block2_01', 'unassisted'),
                                     ('block3_00', 'assisted'), ('block3_01', 'assisted')]
    for name, condition, cues, assisted in seen:
        on = condition == 'assisted_cues'
        assert cues == {n: on for n in CUE_PARAMETERS}, name
        assert assisted == (condition != 'unassisted'), name
    g.step('survey', answers={str(q['id']): ([] if q['kind'] == 'multi' else 1) for q in SURVEY})
    assert g.driver.session.phase == 'done'
    with open(tmp_path / 'P03' / 'landings.csv', newline='') as fh:
        table = list(csv.DictReader(fh))
    assert len(table) == 7
    for r in table:
        assert float(r['path_length_m']) == pytest.approx(TRACK_M, abs=1e-4)   # no teleport, no late sample
        assert (r['key_presses'], r['corrective_keys']) == ('4', '2')
        assert r['assist_live'] == ('false' if r['condition'] == 'unassisted' else 'true')


def test_an_aborted_cue_landing_switches_the_cues_off(graph):
    g = graph
    g.step('begin', participant='P03')
    g.step('consent')
    g.step('start')
    g.until(lambda: g.driver.stage == 'flying', 'the landing in flight')
    assert g.cues() == {n: True for n in CUE_PARAMETERS}
    g.driver.page_lost()
    g.driver.tick()
    assert g.driver.stage == 'idle' and g.cues() == {n: False for n in CUE_PARAMETERS}
    assert g.driver.session.next_landing().name == 'practice_00'        # flown again


def test_without_stamps_a_step_over_a_metre_is_a_teleport(graph):
    g = graph
    g.driver.stage = 'flying'                    # what /sim/reset's answer sets (no landing needed here)
    for p in ((5.0, 5.0, 0.1), (0.0, 0.0, 2.0), (0.6, 0.0, 2.0), (0.6, 0.8, 2.0), (0.6, 2.3, 2.0)):
        g.driver.note_odom(p)
    assert g.driver.path_m == pytest.approx(0.6 + 0.8)
    g.driver.stage = 'idle'
    g.driver.note_odom((0.6, 3.0, 2.0))          # not flying: not part of a landing's path
    assert g.driver.path_m == pytest.approx(0.6 + 0.8)


def test_a_result_that_comes_before_the_resets_answer_is_recorded_when_the_answer_comes(graph, tmp_path):
    """sim_node ends a short landing before its /sim/reset answer reaches the station: the result is kept, not
    dropped (the landing would otherwise wait for a result that already came, then be aborted and flown again)."""
    g = graph
    g.step('begin', participant='P01')
    g.step('consent')
    g.land_before_answer = True
    g.step('start')
    g.until(lambda: g.driver.stage == 'closing', 'the landing recorded')
    assert g.early == [False]                         # held while the answer was on its way, recorded on the answer
    assert g.errors() == []
    with open(tmp_path / 'P01' / 'landings.csv') as f:
        rows = list(csv.DictReader(f))
    assert [(r['block'], r['trial'], r['episode'], r['outcome']) for r in rows] == [('0', '0', '1', 'success')]
    assert [e['text'] for e in g.events if e['type'] == 'landing'] == ['Landing recorded']
    log = (tmp_path / 'P01' / 'protocol.log').read_text()
    assert 'landing_aborted' not in log and log.count('landing_started') == 1
