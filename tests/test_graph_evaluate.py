"""evaluate_graph: evaluate's landings flown through the real node graph (assist_lab.graph_eval).

Five consecutive assisted landings (latent mode, shipped models, paper pilot, five betas), one graph never
restarted between them: most reach the goal pad, none is a timeout that never left the start, each is the
landing evaluate flies for its seed (scene seed and goal pad from episodes_plan), the table is written, and
no node process outlives the run. A second test checks that a failing run still stops its nodes.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from assist_lab import graph_eval
from assist_lab.episodes_plan import landing_plan
from assist_lab.evaluate import read_landings
from assist_sim.core.world import LandingWorld

REPO = Path(__file__).resolve().parents[1]
MODELS = [REPO / 'models' / 'td3_latent_actor.pt', REPO / 'models' / 'cmvae.pt']

pytestmark = [pytest.mark.graph,
              pytest.mark.skipif(not all(m.is_file() for m in MODELS), reason='shipped latent models missing')]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


@pytest.fixture
def started_pids(monkeypatch):
    """Pids of every node graph_eval starts."""
    pids: list[int] = []
    start = graph_eval.NodeGroup.start

    def record(self, executable, *args, **kwargs):
        start(self, executable, *args, **kwargs)
        pids.append(self.procs[executable].pid)
    monkeypatch.setattr(graph_eval.NodeGroup, 'start', record)
    return pids


@pytest.mark.slow(seconds=75)
@pytest.mark.scale
@pytest.mark.timeout(420)
def test_five_consecutive_assisted_landings_through_the_graph(domain_id, tmp_path, started_pids):
    betas = (0.6, 0.7, 0.8, 0.9, 1.0)
    args = graph_eval.GraphEvalArgs(out=str(tmp_path / 'eval'), conditions=('latent',), betas=betas, landings=1,
                                    seed=2024, pilot='paper', real_time_factor=2.0, domain_id=domain_id,
                                    landing_timeout_s=180.0, plot=False)
    summary = graph_eval.evaluate_graph(args)
    name = 'latent+guard+override+recall+damper'                  # evaluate's name for policy_node's defaults
    assert list(summary) == [name] and summary[name]['n'] == 5
    assert len(started_pids) == 4 and not any(_alive(p) for p in started_pids)     # no orphans
    rows = read_landings(tmp_path / 'eval' / 'landings.csv')[name]
    assert [r['seed'] for r in rows] == [2024 + 1000 * b for b in range(5)]
    world = LandingWorld()
    try:
        for r, beta in zip(rows, betas):
            plan = landing_plan(r['seed'], beta, 'paper')
            assert int(r['scene_seed']) == plan.scene_seed and r['pilot'] == 'paper'
            world.reset(seed=plan.scene_seed)
            assert r['goal_index'] == world.goal_index, r                 # sim_node flew the planned scene
            start = np.asarray(world.scene.start_position)
            from_start = float(np.linalg.norm(world.goal_position[:2] - start[:2]))
            # a landing that timed out where it started (the assistant held it there) is a failure
            assert not (r['outcome'] == 'timeout' and abs(r['error_m'] - from_start) < 0.3), r
            assert float(r['duration_s']) > 3.0, r
    finally:
        world.close()
    assert sum(r['outcome'] == 'success' for r in rows) >= 3, rows
    assert (tmp_path / 'eval' / 'summary.csv').is_file()


@pytest.mark.timeout(120)
def test_a_failing_run_stops_its_nodes(domain_id, tmp_path, started_pids):
    # no landing can come in 1 s of wall time: GraphError, and every node it started is gone
    args = graph_eval.GraphEvalArgs(out=str(tmp_path / 'eval'), conditions=('unassisted',), betas=(0.5,), landings=1,
                                    real_time_factor=1.0, domain_id=domain_id, landing_timeout_s=1.0, plot=False)
    with pytest.raises(graph_eval.GraphError, match='no landing 0'):
        graph_eval.evaluate_graph(args)
    assert len(started_pids) == 2 and not any(_alive(p) for p in started_pids)
    assert (tmp_path / 'eval' / 'landings.partial.json').is_file()      # resumable, nothing committed
    assert not (tmp_path / 'eval' / 'landings.csv').exists()


def test_a_second_run_on_a_held_out_is_refused_before_any_node_starts(tmp_path, started_pids, capsys):
    from assist_lab.cluster import hold_directory
    out = tmp_path / 'eval'
    with hold_directory(out, 'evaluate_graph', 'wait'):          # another run holds --out
        code = graph_eval.main(['--out', str(out), '--conditions', 'unassisted', '--betas', '0.5',
                                '--landings', '1', '--plot', 'false'])
    assert code == 2 and started_pids == []
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f'error: {out} is in use by another evaluate_graph run (pid ')
    assert sorted(p.name for p in out.iterdir()) == []          # nothing written, the lock file gone with the holder
