"""Training landings on env workers (assist_lab.collect): what a pool of workers flies, and train_td3 on it."""
import csv
import functools
import os
import signal
import time

import numpy as np
import pytest
import torch

from assist_lab.collect import (ActorWeights, LandingPool, LandingTask, LandingWorker, collect_demos,
                                   make_env)
from assist_lab.cluster import WorkerDied, WorkerPool
from assist_lab.env import EnvConfig
from assist_lab.td3 import TD3, ReplayBuffer, TD3Config, load_actor
from assist_lab.train import TrainArgs, evaluate_agent, load_checkpoint, main, resumed_args, train

pytestmark = pytest.mark.slow(seconds=100)
CFG = dict(condition='oracle', max_episode_s=3.0)


def _agent(obs_dim: int) -> TD3:
    torch.set_num_threads(1)
    return TD3(obs_dim, 3, TD3Config(hidden=(32, 32)), seed=3)


def _buffer_rows(buf: ReplayBuffer) -> tuple:
    n = buf.size
    return tuple(a[:n].copy() for a in (buf.obs, buf.act, buf.rew, buf.next_obs, buf.done))


@pytest.fixture(scope='module')
def pool():
    with LandingPool(EnvConfig(**CFG), 'oracle', 2) as p:
        yield p


def test_two_workers_fly_the_dagger_landings_and_evaluation_of_one_process(pool):
    env = make_env(EnvConfig(**CFG))
    try:
        agent = _agent(env.observation_space.shape[0])
        here, there = (ReplayBuffer(env.observation_space.shape[0], 3, 10_000) for _ in range(2))
        o1, a1, r1 = collect_demos(env, 4, 0.0, 5, here, 'oracle', act_fn=agent.act)
        o2, a2, r2 = collect_demos(env, 4, 0.0, 5, there, 'oracle', act_fn=agent.act, pool=pool,
                                   weights=ActorWeights.of(agent.actor, agent.meta))
        assert len(r1) == 4 and len(o1) > 100
        assert np.array_equal(o1, o2) and np.array_equal(a1, a2) and r1 == r2
        for x, y in zip(_buffer_rows(here), _buffer_rows(there)):
            assert np.array_equal(x, y)
        # the actor flew (DAgger): the flown actions are its own, the labels the oracle's
        assert not np.allclose(here.act[:here.size], a1)
        assert evaluate_agent(env, agent, 1, pool=pool) == evaluate_agent(env, agent, 1)
    finally:
        env.close()


def test_a_pool_gives_what_one_worker_gives_for_noisy_demos_and_td3_landings(pool):
    worker = LandingWorker(EnvConfig(**CFG), 'oracle')
    try:
        agent = _agent(worker.env.observation_space.shape[0])
        weights = ActorWeights.of(agent.actor, agent.meta)
        tasks = [LandingTask('demo', 0, 11, noise_seed=(1, 0), noise=0.3),
                 LandingTask('td3', 1, 12, noise_seed=(1, 1), random_actions=True),
                 LandingTask('td3', 2, 13, noise_seed=(1, 2), ou=(0.15, 0.3, 0.05, 0.997, 40))]
        mine = [worker.fly(t, weights) for t in tasks]
        theirs = list(pool.map(tasks, weights))
        for m, t in zip(mine, theirs):
            assert m.episode == t.episode and m.result == t.result and m.steps == t.steps
            assert np.array_equal(m.obs, t.obs) and np.array_equal(m.act, t.act) and np.array_equal(m.rew, t.rew)
        noisy, random_, ou = mine
        assert noisy.labels is not None and not np.allclose(noisy.act, np.clip(noisy.labels, -1, 1))
        assert random_.labels is None and np.abs(random_.act).max() <= 1.0 and random_.act.std() > 0.4
        assert np.array_equal(noisy.next_obs[:-1], noisy.obs[1:]) and noisy.done[-1] == 1.0
        # the same task flown again is the same landing (its noise comes from its own seed)
        again = worker.fly(tasks[2], weights)
        assert np.array_equal(again.act, ou.act)
        with pytest.raises(ValueError, match='weights'):
            worker.fly(LandingTask('demo', 3, 14, actor_flies=True), None)
    finally:
        worker.close()


def test_replay_buffer_extend_wraps_and_checks_lengths():
    buf = ReplayBuffer(2, 1, capacity=5)
    for k in range(2):
        buf.extend(np.full((3, 2), k), np.full((3, 1), k), np.arange(3), np.full((3, 2), k), np.zeros(3))
    assert buf.size == 5 and buf.ptr == 1
    assert buf.obs[:, 0].tolist() == [1, 0, 0, 1, 1] and buf.rew[:, 0].tolist() == [2, 1, 2, 0, 1]
    buf.extend(np.zeros((7, 2)), np.zeros((7, 1)), np.arange(7), np.zeros((7, 2)), np.zeros(7))
    assert sorted(buf.rew[:, 0].tolist()) == [2, 3, 4, 5, 6]        # only the newest five fit
    with pytest.raises(ValueError, match='different lengths'):
        buf.extend(np.zeros((2, 2)), np.zeros((3, 1)), np.zeros(2), np.zeros((2, 2)), np.zeros(2))


def _run(tmp_path, name: str, **extra) -> TrainArgs:
    settings = dict(runs_dir=str(tmp_path), condition='oracle', total_steps=500, start_steps=150, max_episode_s=4.0,
                    eval_every_episodes=4, eval_episodes_per_beta=1, hidden=(32, 32), buffer_size=5000,
                    checkpoint_every_steps=300, demo_episodes=2, dagger_rounds=1, dagger_episodes=2, bc_steps=20,
                    seed=3)
    return TrainArgs(name=name, **{**settings, **extra})


def _rows(path) -> list[dict]:
    with open(path, newline='') as fh:
        return [{k: v for k, v in r.items() if k != 'wall_s'} for r in csv.DictReader(fh)]


def test_train_td3_on_two_workers_is_a_complete_deterministic_run(tmp_path):
    runs = [train(_run(tmp_path, name, workers=2)) for name in ('a', 'b')]
    metrics = [_rows(r / 'metrics.csv') for r in runs]
    assert metrics[0] == metrics[1]                                  # a function of the seed and the worker count
    assert _rows(runs[0] / 'eval.csv') == _rows(runs[1] / 'eval.csv')
    state, _ = load_checkpoint(runs[0])
    assert state['step'] >= 500 and state['episode'] == len(metrics[0])
    assert [int(r['episode']) for r in metrics[0]] == list(range(1, len(metrics[0]) + 1))
    assert int(metrics[0][-2]['step']) < 500 <= int(metrics[0][-1]['step'])     # stops at the crossing landing
    assert any(r['critic_loss'] for r in metrics[0])                 # the learner updated on the workers' data
    assert (runs[0] / 'progress.txt').is_file() and load_actor(runs[0] / 'actor_best.pt')[1]['eval']
    assert (runs[0] / 'learning_curve.png').is_file() and (runs[0] / 'demos_bc.npz').is_file()


def test_a_resumed_run_may_change_its_workers(tmp_path):
    run = train(_run(tmp_path, 'w', total_steps=200, demo_episodes=0, dagger_rounds=0, bc_steps=0))
    resumed = resumed_args(TrainArgs(resume=str(run), workers=3, ray='auto'), given={'resume', 'workers', 'ray'})
    assert resumed.workers == 3 and resumed.ray == 'auto' and resumed.seed == 3


def test_ray_at_an_address_nobody_serves_is_one_error_line(tmp_path, capsys):
    pytest.importorskip('ray', reason='ray is in requirements.txt; this runs wherever make test installed it')
    with pytest.raises(SystemExit) as exc:
        main(['--runs-dir', str(tmp_path), '--name', 'r', '--ray', '127.0.0.1:1', '--total-steps', '10'])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert 'cannot start or reach Ray' in err and 'Traceback' not in err
    assert not (tmp_path / 'r').exists()                     # refused before the run directory is made


@pytest.mark.scale
def test_ray_actors_fly_what_a_local_worker_flies(local_ray):
    worker = LandingWorker(EnvConfig(**CFG), 'oracle')
    tasks = [LandingTask('demo', k, 20 + k, noise_seed=(2, k), noise=0.2) for k in range(2)]
    try:
        mine = [worker.fly(t, None) for t in tasks]
        with LandingPool(EnvConfig(**CFG), 'oracle', 2, ray_address='auto') as pool:
            theirs = list(pool.map(tasks))
        for m, t in zip(mine, theirs):
            assert m.result == t.result and np.array_equal(m.obs, t.obs) and np.array_equal(m.act, t.act)
    finally:
        worker.close()


@pytest.mark.scale
def test_a_second_ray_address_in_one_process_is_refused(local_ray):
    from assist_lab.cluster import connect_ray
    assert connect_ray('auto') is local_ray                        # the instance up for 'auto' is reused
    gcs = local_ray.get_runtime_context().gcs_address              # a Ray answers there, but under another name
    with pytest.raises(ValueError, match='already uses Ray at auto'):
        connect_ray(gcs)


def _group_of(pid: int) -> int | None:
    """Process group of a live process `pid` (None once it is gone or a zombie: exited, not yet reaped by the
    init process it was handed to)."""
    from pathlib import Path
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return None
    return None if fields[0] in ('Z', 'X') else int(fields[2])


def test_ctrl_c_stops_a_run_on_workers_quietly_and_it_resumes(tmp_path):
    """Ctrl-C (SIGINT to the process group, as a terminal sends it): train_td3 and its workers stop within
    seconds, exit status 130, no traceback from any worker, no process left; --resume continues the run."""
    import os
    import signal
    import subprocess
    import sys
    import time
    from pathlib import Path
    cmd = [str(Path(sys.executable).parent / 'train_td3'), '--runs-dir', str(tmp_path), '--name', 'r',
           '--condition', 'oracle', '--total-steps', '200000', '--start-steps', '100', '--max-episode-s', '4',
           '--hidden', '32', '32', '--buffer-size', '50000', '--checkpoint-every-steps', '300',
           '--eval-every-episodes', '100000', '--workers', '2']
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    metrics = tmp_path / 'r' / 'metrics.csv'
    try:
        end = time.monotonic() + 180
        while time.monotonic() < end and proc.poll() is None:
            if (tmp_path / 'r' / 'checkpoint').is_dir() and metrics.is_file() and len(_rows(metrics)) >= 6:
                break
            time.sleep(0.2)
        assert proc.poll() is None, proc.communicate()[0][-3000:]
        os.killpg(proc.pid, signal.SIGINT)
        out, _ = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)
    assert proc.returncode == 130, out[-3000:]
    assert 'Traceback' not in out and 'KeyboardInterrupt' not in out, out[-3000:]
    end = time.monotonic() + 10                     # a worker or the resource tracker may still be exiting
    while True:
        left = [pid for pid in os.listdir('/proc') if pid.isdigit() and _group_of(int(pid)) == proc.pid]
        if not left or time.monotonic() > end:
            break
        time.sleep(0.1)
    assert not left, [(pid, Path(f'/proc/{pid}/stat').read_text()) for pid in left]
    step = load_checkpoint(tmp_path / 'r')[0]['step']
    train(TrainArgs(resume=str(tmp_path / 'r'), total_steps=step + 200, workers=1))
    assert load_checkpoint(tmp_path / 'r')[0]['step'] >= step + 200


@pytest.mark.parametrize('waiting', ['completed_in_turn', 'result_of'])
def test_a_ctrl_c_taken_by_another_thread_is_raised_while_waiting_for_workers(waiting):
    """The kernel may hand the terminal's SIGINT to any thread of the process (the pool's); the main
    thread, waiting for a landing, must raise it within a poll period, not when the landing ends."""
    import signal
    import threading
    import time
    from concurrent.futures import ThreadPoolExecutor

    from assist_lab import cluster
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    sent = []

    def to_this_thread():
        sent.append(time.monotonic())
        signal.pthread_kill(threading.get_ident(), signal.SIGINT)
    with ThreadPoolExecutor(1) as pool:
        landing = pool.submit(time.sleep, 4.0)
        threading.Timer(0.3, to_this_thread).start()
        try:
            with pytest.raises(KeyboardInterrupt):
                if waiting == 'result_of':
                    cluster.result_of(landing)
                else:
                    list(cluster.completed_in_turn([landing]))
            assert time.monotonic() - sent[0] < 2.0
        finally:
            signal.signal(signal.SIGINT, previous)


def test_a_worker_is_deaf_to_ctrl_c_from_its_birth_and_the_parent_is_not():
    """A Ctrl-C that reaches a worker while it still starts (before its initializer) neither kills it nor prints a
    traceback: workers are born with SIGINT blocked; the parent's own mask is left as it was."""
    from assist_lab import cluster
    ctx = cluster.process_context()
    before = signal.pthread_sigmask(signal.SIG_BLOCK, [])
    proc = ctx.Process(target=time.sleep, args=(0.5,))
    proc.start()
    os.kill(proc.pid, signal.SIGINT)              # at once: the child is still importing
    proc.join(60)
    assert proc.exitcode == 0
    assert signal.pthread_sigmask(signal.SIG_BLOCK, []) == before and signal.SIGINT not in before
    with cluster.ProcessPoolExecutor(1, mp_context=ctx) as pool:
        assert signal.SIGINT in pool.submit(signal.pthread_sigmask, signal.SIG_BLOCK, []).result(60)


def test_completed_in_turn_yields_each_future_once_in_completion_order():
    import time
    from concurrent.futures import ThreadPoolExecutor

    from assist_lab import cluster
    with ThreadPoolExecutor(3) as pool:
        futures = [pool.submit(time.sleep, s) for s in (0.6, 0.05, 0.3)]
        order = [futures.index(f) for f in cluster.completed_in_turn(futures)]
    assert order == [1, 2, 0]
    with ThreadPoolExecutor(1) as pool:
        failing = pool.submit(int, 'x')
        assert list(cluster.completed_in_turn([failing])) == [failing]
        with pytest.raises(ValueError):
            cluster.result_of(failing)


def test_actor_weights_cross_to_a_worker_by_value_without_handing_over_file_descriptors():
    # torch tensors pickled for another process travel as shared-memory file descriptors through
    # multiprocessing's resource sharer, whose hand-over a worker killed mid-way turned into a
    # traceback in the learner; the snapshot is pickled by value instead (a fresh interpreter, so no
    # other test has started the sharer)
    code = '''
import torch
from multiprocessing import resource_sharer
from multiprocessing.reduction import ForkingPickler
import pickle
from assist_lab.collect import ActorWeights
from assist_lab.td3 import TD3, TD3Config
agent = TD3(5, 3, TD3Config(hidden=(8, 8)), seed=3)
w = ActorWeights.of(agent.actor, agent.meta)
data = bytes(ForkingPickler.dumps(w))
back = pickle.loads(data)
same = back.policy()([0.1] * 5).tolist() == w.policy()([0.1] * 5).tolist()
print(resource_sharer._resource_sharer._listener is None, same)
'''
    import subprocess
    import sys
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ['True', 'True'], out.stdout


def test_a_worker_killed_while_it_writes_a_result_is_one_error_and_the_pool_still_closes():
    """A worker SIGKILLed in the middle of sending its result leaves the executor's manager thread waiting for the
    rest of that message, so the executor itself never says it is broken: the pool sees the process end, raises
    WorkerDied at once, and its close() ends that thread (the program can exit)."""
    import struct
    import types
    pool = WorkerPool(functools.partial(types.SimpleNamespace, fly=time.sleep), 2)
    try:
        handle = pool.submit(60.0)
        deadline = time.monotonic() + 60
        while not pool._pool._processes and time.monotonic() < deadline:      # the executor starts them lazily
            time.sleep(0.05)
        manager = pool._pool._executor_manager_thread
        writer = pool._pool._result_queue._writer
        os.write(writer.fileno(), struct.pack('!i', 1_000_000) + b'x' * 10)      # a result cut short
        time.sleep(0.5)
        os.kill(next(iter(pool._pool._processes)), signal.SIGKILL)
        t0 = time.monotonic()
        with pytest.raises(WorkerDied, match=r'a worker process died \(pid \d+, killed by SIGKILL\)'):
            pool.result(handle)
        assert time.monotonic() - t0 < 10
    finally:
        pool.close()
    manager.join(10)
    assert not manager.is_alive()
