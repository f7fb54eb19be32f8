"""Fork server for the documented-commands test (tests/test_documented_commands.py; tests only).

`doc_forkserver.py SOCKET`: imports torch and the lab's tools once, then runs each command-line tool call that
tests/standins/doc_shim.py hands it in a forked child, so a call costs its work and not another interpreter and
torch start-up (~3 s each on a 2-core machine; the documents make ~80 calls). The shim passes its stdin, stdout and
stderr (SCM_RIGHTS) and a JSON line {program, args, cwd, env}; the child takes those as its own, runs the
program's console-script entry point as the installed executable would (sys.argv, exit status from its return
value or SystemExit) and answers the exit status as one line. The server forks before any thread or rclpy
context exists in it (checked at start); node executables and the bag recorder/player are never forked (the shim
starts them as processes).
"""
from __future__ import annotations

import importlib
import importlib.metadata
import json
import os
import signal
import socket
import sys
import threading
import traceback

# what the tools import, loaded once (none of it starts a thread: checked before the first fork); torch._dynamo is
# what a torch optimizer's first use imports (~2 s in each training call)
PRELOAD = ('torch', 'torch._dynamo', 'torch.onnx', 'onnx', 'onnxruntime', 'numpy', 'matplotlib', 'matplotlib.pyplot',
           'pybullet',
           'assist_perception.encoder_core', 'assist_lab.evaluate', 'assist_lab.train', 'assist_lab.graph_eval',
           'assist_lab.compare', 'assist_lab.cmvae_train', 'assist_bags.replay', 'assist_station.simulate_study',
           'assist_station.analyze_study')
MAX_REQUEST = 1 << 20


def entry_point(program: str):
    """The console-script function of `program` (as the installed executable runs it)."""
    found = importlib.metadata.entry_points(group='console_scripts', name=program)
    if not found:
        raise LookupError(f'no console script {program!r}')
    return next(iter(found)).load()


def child(conn: socket.socket, request: dict, fds: list[int]) -> None:
    """Become the program: its standard streams, directory, environment and argv; answer its exit status."""
    code = 1
    try:
        for target, fd in zip((0, 1, 2), fds):
            os.dup2(fd, target)
            os.close(fd)
        os.chdir(request['cwd'])
        os.environ.clear()
        os.environ.update(request['env'])
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        sys.argv = [request['program'], *request['args']]
        try:
            result = entry_point(request['program'])()
            code = result if isinstance(result, int) else 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            if not isinstance(exc.code, int) and exc.code is not None:
                sys.stderr.write(f'{exc.code}\n')
    except BaseException:  # noqa: BLE001 - reported as the program's own traceback and exit status 1
        traceback.print_exc()
        code = 1
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        try:
            conn.sendall(f'{code}\n'.encode())
        finally:
            os._exit(code)


def serve(path: str) -> None:
    """Accept calls on the UNIX socket `path` until killed; fork one child per call."""
    for name in PRELOAD:
        importlib.import_module(name)
    if threading.active_count() != 1:
        raise SystemExit(f'doc_forkserver: {threading.active_count()} threads after the imports: forking is unsafe')
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)      # children are reaped by the kernel
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    server.bind(path + '.tmp')
    server.listen(16)
    os.rename(path + '.tmp', path)                      # the socket appears once it accepts
    while True:
        conn, _ = server.accept()
        try:
            data, fds, _, _ = socket.recv_fds(conn, MAX_REQUEST, 3)
            while len(data) < MAX_REQUEST and (more := conn.recv(MAX_REQUEST)):    # the rest, up to the shim's EOF
                data += more
            request = json.loads(data.decode())
        except (OSError, ValueError) as exc:
            sys.stderr.write(f'doc_forkserver: bad request: {exc}\n')
            conn.close()
            continue
        if os.fork() == 0:
            server.close()
            child(conn, request, fds)
        for fd in fds:
            os.close(fd)
        conn.close()


def call(path: str, program: str, args: list[str]) -> int:
    """Run `program args` in the fork server at `path` with this process's streams, directory and environment."""
    request = json.dumps({'program': program, 'args': args, 'cwd': os.getcwd(), 'env': dict(os.environ)}).encode()
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as conn:
        conn.connect(path)
        socket.send_fds(conn, [request], [0, 1, 2])
        conn.shutdown(socket.SHUT_WR)
        answer = b''
        while chunk := conn.recv(64):
            answer += chunk
    try:
        return int(answer.decode().strip())
    except ValueError:
        sys.stderr.write(f'{program}: the forked run ended without an exit status (killed?)\n')
        return 1


if __name__ == '__main__':
    serve(sys.argv[1])
