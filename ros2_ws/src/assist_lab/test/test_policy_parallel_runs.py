"""evaluate and train_td3 running on worker processes: one run per output directory, a --ray address that is
not Ray, a worker that dies, a parent that is SIGKILLed, and rows that do not depend on the worker count."""
from __future__ import annotations

import csv
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from assist_lab import evaluate as ev
from assist_lab import train as tr
from assist_lab import cluster

BIN = Path(sys.executable).parent
# an unassisted plan long enough to act on while it runs: its landings take about a second each
EVAL_FLAGS = ['--conditions', 'unassisted', '--betas', '0', '1', '--landings', '4', '--max-episode-s', '20',
              '--plot', 'false']
EVAL_LANDINGS = 8
TRAIN_FLAGS = ['--condition', 'oracle', '--total-steps', '200000', '--start-steps', '100', '--max-episode-s', '4',
               '--hidden', '32', '32', '--buffer-size', '50000', '--checkpoint-every-steps', '300',
               '--eval-every-episodes', '100000']
START_S = 240          # generous: the workers import torch and build their worlds on a shared, loaded machine


def _stat(pid: int) -> list[str] | None:
    """/proc/<pid>/stat's fields after the command name (state first), or None once it is gone or a zombie."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
    except OSError:
        return None
    return None if fields[0] in ('Z', 'X') else fields


def _children(pid: int) -> list[int]:
    """Live child processes of `pid`."""
    out = []
    for name in os.listdir('/proc'):
        if name.isdigit():
            fields = _stat(int(name))
            if fields is not None and int(fields[1]) == pid:
                out.append(int(name))
    return out


def _workers(pid: int) -> list[int]:
    """The multiprocessing workers `pid` spawned (not its resource tracker)."""
    found = []
    for child in _children(pid):
        try:
            if b'spawn_main' in Path(f'/proc/{child}/cmdline').read_bytes():
                found.append(child)
        except OSError:
            continue
    return found


def _rows(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    with open(path, newline='', encoding='utf-8') as fh:
        return [r for r in csv.DictReader(fh)]


def _wait_for(what, proc: subprocess.Popen, log: Path, timeout_s: float = START_S):
    """Poll `what()` until it is true while `proc` runs (a 0.2 s poll: the run is another process)."""
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        value = what()
        if value:
            return value
        assert proc.poll() is None, log.read_text()[-3000:]
        time.sleep(0.2)
    raise AssertionError(f'timed out; its output: {log.read_text()[-3000:]}')


def _start(cmd: list[str], log: Path) -> subprocess.Popen:
    """A tool in its own session (its workers in its process group), its output in `log`."""
    with open(log, 'w') as fh:
        return subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True,
                                env={**os.environ, 'PYTHONUNBUFFERED': '1'})


def _stop(proc: subprocess.Popen) -> None:
    """Kill whatever is left of the run's process group."""
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait(30)


# ----------------------------------------------------------------------------- one run per directory
def test_a_second_evaluate_on_the_same_out_is_refused_and_the_first_run_keeps_its_landings(tmp_path, capsys):
    out = tmp_path / 'ev'
    log = tmp_path / 'first.log'
    first = _start([str(BIN / 'evaluate'), '--out', str(out), '--workers', '1', *EVAL_FLAGS], log)
    try:
        _wait_for(lambda: len(_rows(out / 'landings.partial.csv')) >= 1, first, log)
        # other settings, same directory: it would have removed the first run's landings.partial.csv
        code = ev.main(['--out', str(out), '--conditions', 'unassisted', '--betas', '0.25', '--landings', '1',
                        '--plot', 'false'])
        err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert code == 2
        assert err == [f'error: {out} is in use by another evaluate run (pid {first.pid}): wait for it to end, '
                       'or choose another --out'], err
        assert first.wait(300) == 0, log.read_text()[-3000:]
    finally:
        _stop(first)
    rows = _rows(out / 'landings.csv')
    assert len(rows) == EVAL_LANDINGS and {r['beta'] for r in rows} == {'0.0', '1.0'}    # all the first run's
    assert not (out / '.evaluate.lock').exists()
    assert ev.main(['--out', str(out), '--conditions', 'unassisted', '--betas', '0.25', '--landings', '1',
                    '--plot', 'false', '--max-episode-s', '2']) == 0                  # free again once it ended


def test_a_killed_evaluate_leaves_no_lock_behind(tmp_path):
    """The kernel drops a SIGKILLed run's lock: the file it leaves does not block the next run."""
    out = tmp_path / 'ev'
    holder = subprocess.Popen([sys.executable, '-c', 'import sys, time\n'
                               'from assist_lab.cluster import hold_directory\n'
                               f'with hold_directory({str(out)!r}, "evaluate", ""):\n'
                               '    print("held", flush=True)\n'
                               '    time.sleep(600)\n'], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == 'held'
        with pytest.raises(cluster.DirectoryBusy, match=f'pid {holder.pid}'):
            with cluster.hold_directory(out, 'evaluate', ''):
                pass
    finally:
        holder.kill()
        holder.wait(30)
    assert (out / '.evaluate.lock').exists()
    with cluster.hold_directory(out, 'evaluate', ''):
        assert (out / '.evaluate.lock').read_text().strip() == str(os.getpid())
    assert not (out / '.evaluate.lock').exists()


# ----------------------------------------------------------------------------- --ray at something that is not Ray
class _FakeServer:
    """A TCP server on 127.0.0.1 that accepts every connection and then says nothing, or `greeting`."""

    def __init__(self, greeting: bytes = b'') -> None:
        self.sock = socket.create_server(('127.0.0.1', 0))
        self.greeting, self.conns = greeting, []
        self.address = f'127.0.0.1:{self.sock.getsockname()[1]}'
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self.sock.accept()
            except OSError:
                return
            self.conns.append(conn)
            if self.greeting:
                conn.sendall(self.greeting)

    def close(self) -> None:
        self.sock.close()
        for conn in self.conns:
            conn.close()


@pytest.mark.parametrize('greeting, said', [(b'', 'no gRPC answer within'),
                                            (b'220 mail.example ESMTP ready\r\n', "it answered b'220 mail")])
def test_ray_at_a_port_that_is_not_ray_is_one_error_line_at_once(greeting, said, tmp_path):
    pytest.importorskip('ray', reason='ray is in requirements.txt; this runs wherever make test installed it')
    server = _FakeServer(greeting)
    cmd = [str(BIN / 'evaluate'), '--out', str(tmp_path / 'x'), '--ray', server.address, '--conditions',
           'unassisted', '--betas', '0', '--landings', '1', '--plot', 'false']
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=60)         # Ray alone retried such an address for minutes
    finally:
        _stop(proc)
        server.close()
    assert proc.returncode == 2, err[-3000:]
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f'error: --ray {server.address}: cannot start or reach Ray: '
                                                   f'{server.address}'), err
    assert said in lines[0] and 'written' not in out
    assert not (tmp_path / 'x' / 'landings.partial.json').exists()


# ----------------------------------------------------------------------------- a worker that dies
def test_a_killed_evaluate_worker_is_one_line_and_the_same_command_resumes(tmp_path, caplog):
    out = tmp_path / 'ev'
    flags = ['--out', str(out), '--workers', '2', *EVAL_FLAGS]
    log = tmp_path / 'run.log'
    proc = _start([str(BIN / 'evaluate'), *flags], log)
    try:
        _wait_for(lambda: len(_rows(out / 'landings.partial.csv')) >= 1, proc, log)
        victim = _wait_for(lambda: _workers(proc.pid), proc, log)[0]
        os.kill(victim, signal.SIGKILL)
        assert proc.wait(120) == 1, log.read_text()[-3000:]
    finally:
        _stop(proc)
    text = log.read_text()
    assert 'Traceback' not in text and 'BrokenProcessPool' not in text, text[-3000:]
    errors = [line for line in text.splitlines() if line.startswith('error:')]
    assert errors == [f'error: a worker process died (pid {victim}, killed by SIGKILL); the landings flown so far '
                      f'are kept in {out / "landings.partial.csv"}: re-running the same command resumes'], text[-3000:]
    kept = len(_rows(out / 'landings.partial.csv'))
    assert kept >= 1
    caplog.set_level('INFO', logger='assist_lab.evaluate')
    assert ev.main(flags) == 0
    assert f'resuming: {kept} landings already flown' in caplog.text
    assert len(_rows(out / 'landings.csv')) == EVAL_LANDINGS


def test_a_killed_train_td3_worker_is_one_line_and_its_directory_is_held_while_it_runs(tmp_path, capsys):
    run = tmp_path / 'r'
    log = tmp_path / 'run.log'
    proc = _start([str(BIN / 'train_td3'), '--runs-dir', str(tmp_path), '--name', 'r', *TRAIN_FLAGS,
                   '--workers', '2'], log)
    try:
        _wait_for(lambda: len(_rows(run / 'metrics.csv')) >= 2, proc, log)
        # a resume of the run while it runs (or a new run of that name before it has written config.json)
        with pytest.raises(SystemExit) as exc:
            tr.main(['--resume', str(run), '--total-steps', '10'])
        assert exc.value.code == 2
        # (log lines before it reach stderr too where an earlier test configured logging in this process)
        err = [line for line in capsys.readouterr().err.splitlines() if 'error:' in line]
        assert err == [f'train_td3: error: {run} is in use by another train_td3 run (pid {proc.pid}): wait for it '
                       'to end, or choose another --name'], err
        victim = _wait_for(lambda: _workers(proc.pid), proc, log)[0]
        os.kill(victim, signal.SIGKILL)
        assert proc.wait(120) == 1, log.read_text()[-3000:]
    finally:
        _stop(proc)
    text = log.read_text()
    assert 'Traceback' not in text and 'BrokenProcessPool' not in text, text[-3000:]
    errors = [line for line in text.splitlines() if 'error:' in line]
    assert errors == [f'train_td3: error: a worker process died (pid {victim}, killed by SIGKILL); continue the run '
                      f'from its last checkpoint with: train_td3 --resume {run}'], text[-3000:]
    with cluster.hold_directory(run, 'train_td3', ''):          # released with the process
        pass


# ----------------------------------------------------------------------------- a parent that is SIGKILLed
@pytest.mark.parametrize('tool', ['evaluate', 'train_td3'])
def test_workers_end_when_their_parent_is_sigkilled(tool, tmp_path):
    if not Path('/proc/self/stat').exists():
        pytest.skip('reads the process table from /proc')
    log = tmp_path / 'run.log'
    if tool == 'evaluate':
        cmd = [str(BIN / 'evaluate'), '--out', str(tmp_path / 'ev'), '--workers', '2', *EVAL_FLAGS]
        started = tmp_path / 'ev' / 'landings.partial.csv'
    else:
        cmd = [str(BIN / 'train_td3'), '--runs-dir', str(tmp_path), '--name', 'r', *TRAIN_FLAGS, '--workers', '2']
        started = tmp_path / 'r' / 'metrics.csv'
    proc = _start(cmd, log)
    try:
        _wait_for(lambda: len(_rows(started)) >= 1, proc, log)
        workers = _wait_for(lambda: len(_workers(proc.pid)) == 2 and _workers(proc.pid), proc, log)
        children = _children(proc.pid)          # the workers and multiprocessing's resource tracker
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(30)
        end = time.monotonic() + 60             # the kernel ends them at once; the bound only spares slow machines
        while any(_stat(pid) is not None for pid in children) and time.monotonic() < end:
            time.sleep(0.1)
        left = [(pid, Path(f'/proc/{pid}/cmdline').read_bytes()[:200]) for pid in children if _stat(pid) is not None]
        assert not left, left
        assert set(workers) <= set(children)
    finally:
        _stop(proc)


# ----------------------------------------------------------------------------- rows whatever the worker count
def test_rows_are_the_same_whatever_landings_a_process_flew_before(tmp_path):
    """The second landing of this plan (seed 2024, beta 0) lasts 20.525 s: one process that flew the first landing
    before it wrote 20.53, a fresh worker 20.52 (the world clock's rounding). One process, two workers and the
    landing flown alone give the same rows."""
    flags = ['--conditions', 'unassisted', '--betas', '0.5', '0', '--landings', '1', '--seed', '1024', '--plot',
             'false']
    assert ev.main(['--out', str(tmp_path / 'one'), '--workers', '1', *flags]) == 0
    assert ev.main(['--out', str(tmp_path / 'two'), '--workers', '2', *flags]) == 0
    assert ev.main(['--out', str(tmp_path / 'alone'), '--workers', '1', '--conditions', 'unassisted', '--betas', '0',
                    '--landings', '1', '--seed', '2024', '--plot', 'false']) == 0
    one, two, alone = (_rows(tmp_path / name / 'landings.csv') for name in ('one', 'two', 'alone'))
    assert [(r['beta'], r['seed']) for r in one] == [('0.5', '1024'), ('0.0', '2024')]
    assert one == two
    assert one[1] == alone[0]
