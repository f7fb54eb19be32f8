"""run_node's teardown after a stop signal is bounded: TeardownDeadline ends a process whose node destruction
hangs in C with the GIL held (rcl_node_fini deleting the middleware's participant), with run_node's exit code
and every thread's stack, instead of waiting for launch's SIGKILL."""
import os
import signal
import subprocess
import sys
import textwrap

import rclpy
from rclpy.node import Node
from assist_common.domains import private_domain_id

WAIT_S = 60.0       # a hung process would sleep 600 s: any bound far below that tells the two apart


def _run(script: str, tmp_path, signal_after_line: str | None = None) -> tuple[int, list[str], str]:
    """Run `script` on a private domain, SIGINT it once it printed `signal_after_line`: exit code, the lines it
    printed that start with 'probe: ' (without it; the middleware may print lines of its own), stderr."""
    path = tmp_path / 'script.py'
    path.write_text(textwrap.dedent(script))
    err_path = tmp_path / 'stderr.txt'
    with open(err_path, 'w') as err:
        proc = subprocess.Popen([sys.executable, str(path)], stdout=subprocess.PIPE, stderr=err, text=True,
                                env={**os.environ, 'ROS_DOMAIN_ID': str(private_domain_id())})
    try:
        lines = []
        if signal_after_line is not None:
            for line in proc.stdout:
                lines.append(line)
                if line.strip() == 'probe: ' + signal_after_line:
                    proc.send_signal(signal.SIGINT)
                    break
        out, _ = proc.communicate(timeout=WAIT_S)
    finally:
        proc.kill()
        proc.wait(10)
    printed = [ln[len('probe: '):] for ln in (''.join(lines) + out).splitlines() if ln.startswith('probe: ')]
    return proc.returncode, printed, err_path.read_text()


def test_a_deadline_ends_a_process_whose_gil_is_held_with_the_given_code_and_its_stacks(tmp_path):
    code, out, err = _run('''
        import ctypes
        from assist_common.ros_run import TeardownDeadline
        deadline = TeardownDeadline.arm(0.5, 3)
        print('probe: armed', deadline.armed, flush=True)
        ctypes.PyDLL(None).sleep(600)       # PyDLL keeps the GIL during the call: no Python code runs any more
        print('probe: not reached', flush=True)
    ''', tmp_path)
    assert code == 3, (out, err)
    assert out == ['armed True'], out
    assert 'Timeout (0:00:00.500000)!' in err, err
    assert 'line 6 in <module>' in err, err          # where it was stuck: the sleep


def test_a_cancelled_deadline_neither_exits_nor_writes_stacks(tmp_path):
    code, out, err = _run('''
        import sys, time
        from assist_common.ros_run import TeardownDeadline
        deadline = TeardownDeadline.arm(0.3, 3)
        deadline.cancel()
        print('probe: cancelled, armed', deadline.armed, flush=True)
        time.sleep(1.5)                      # past the deadline and its dump lead
        print('probe: still running', flush=True)
        sys.exit(7)
    ''', tmp_path)
    assert code == 7, (out, err)
    assert out == ['cancelled, armed False', 'still running'], out
    assert 'Timeout' not in err, err


STUCK_DESTROY = '''
    import ctypes, sys
    from rclpy.node import Node
    import assist_common.ros_run as rc
    import assist_common.ros_params as rp
    rc.TEARDOWN_DEADLINE_S = 1.0

    class N(Node):
        """Its destruction blocks in C holding the GIL, as rcl_node_fini did in CI (Fast DDS participant deletion)."""
        def __init__(self):
            super().__init__('stuck_destroy_probe')
            rp.declare_parameters(self, {'executor': rc.executor_param('events')})
            self.create_timer(0.05, self.tick)
            self.ticked = False

        def tick(self):
            if not self.ticked:
                self.ticked = True
                print('probe: up', flush=True)

        def close(self):
            print('probe: closed', flush=True)

        def destroy_node(self):
            print('probe: destroying', flush=True)
            ctypes.PyDLL(None).sleep(600)

    rc.exit_process(rc.run_node(N, sys.argv[1:]))
'''


def test_a_node_whose_destruction_hangs_after_ctrl_c_exits_0_within_the_deadline_with_its_stacks(tmp_path):
    """Before: the process waited in destroy_node until launch's SIGKILL (exit -9, an ERROR line in the launch)."""
    code, out, err = _run(STUCK_DESTROY, tmp_path, signal_after_line='up')
    assert code == 0, (out, err)
    assert out == ['up', 'closed', 'destroying'], out     # the node's close() ran before
    assert 'Timeout (0:00:01)!' in err, err
    assert 'in destroy_node' in err and 'in run_node' in err, err       # the stuck thread's stack


def _recording_script(body: str) -> str:
    """`body` after a prologue that keeps every TeardownDeadline run_node arms in the list `deadlines`."""
    return textwrap.dedent('''
        import sys
        from rclpy.node import Node
        import assist_common.ros_run as rc
        import assist_common.ros_params as rp

        deadlines = []
        arm = rc.TeardownDeadline.arm
        def recording_arm(seconds, code):
            deadlines.append(arm(seconds, code))
            return deadlines[-1]
        rc.TeardownDeadline.arm = recording_arm
    ''') + textwrap.dedent(body)


def test_run_node_cancels_the_deadline_once_the_node_is_destroyed(tmp_path):
    code, out, err = _run(_recording_script('''
        class N(Node):
            def __init__(self):
                super().__init__('teardown_probe')
                self.create_timer(0.05, self.tick)
                self.ticked = False

            def tick(self):
                if not self.ticked:
                    self.ticked = True
                    print('probe: up', flush=True)

            def destroy_node(self):
                print('probe: destroying; deadline armed:', [d.armed for d in deadlines], flush=True)
                super().destroy_node()

        code = rc.run_node(N, sys.argv[1:])
        print('probe: run_node returned', code, '; deadline armed:', [d.armed for d in deadlines], flush=True)
        sys.exit(5)
    '''), tmp_path, signal_after_line='up')
    assert code == 5, (out, err)
    assert out == ['up', 'destroying; deadline armed: [True]',
                                'run_node returned 0 ; deadline armed: [False]'], out
    assert 'Timeout' not in err, err


class _ShutdownSpinner:
    """The context goes down under spin_once (no stop signal): the RuntimeError race run_node treats as shutdown."""

    def add_node(self, node):
        self.node = node

    def spin_once(self, timeout_sec=None):
        rclpy.try_shutdown()
        raise RuntimeError("Unable to convert call argument '0' to Python object")

    def shutdown(self):
        pass


def test_without_a_stop_signal_run_node_arms_no_deadline(monkeypatch):
    """A process that runs a node in turn with other work (a test run) is never ended by the deadline."""
    import assist_common.ros_run as rc
    armed = []
    monkeypatch.setattr(rc, 'make_executor', lambda kind, num_threads=2: _ShutdownSpinner())
    monkeypatch.setattr(rc.TeardownDeadline, 'arm', classmethod(lambda cls, seconds, code: armed.append(code)))
    monkeypatch.setenv('ROS_DOMAIN_ID', str(private_domain_id()))
    assert rc.run_node(lambda: Node('no_deadline_probe'), args=[]) == 0
    assert armed == []
    assert not rclpy.ok()
