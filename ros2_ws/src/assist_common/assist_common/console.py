"""Console-script entry points that start quietly (standard library only, imported before anything heavy).

A console script imports its module before calling its `main`; a node's module imports rclpy and torch,
which takes seconds, and a Ctrl-C in those seconds (a terminal's, or the SIGINT `ros2 launch` sends every
process when a sibling fails at start-up) would print a KeyboardInterrupt traceback from inside torch.
Each package's `entry_points` module names its executables with `quiet_main`: the module is imported
when the program runs, and a Ctrl-C before `main` has installed its own handling ends the program
without a traceback. While importing, SIGINT exits at once (nothing is open yet): a KeyboardInterrupt
raised inside a C extension's initialisation comes out as an unrelated ImportError (rclpy's
"C extension ... isn't present on the system"), so catching it would not be enough. A node's `--version`
is answered here, before the import (the version is the package's, not the module's).
"""
from __future__ import annotations

import importlib
import importlib.metadata
import logging
import os
import signal
import sys
import typing
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable

#: Exit code of a ROS node stopped by Ctrl-C: it did what was asked, as run_node returns after a Ctrl-C.
NODE_INTERRUPTED = 0
#: Exit code of a command-line tool stopped by Ctrl-C (the shell convention, 128 + SIGINT).
TOOL_INTERRUPTED = 130
HELP_FLAGS = ('-h', '--help')
VERSION_FLAG = '--version'


def package_version(package: str) -> str:
    """Version of an installed package: its Python distribution's, else its package.xml's in the ament index."""
    try:
        return importlib.metadata.version(package)
    except importlib.metadata.PackageNotFoundError:
        pass
    try:
        from ament_index_python.packages import get_package_share_directory
        version = ET.parse(os.path.join(get_package_share_directory(package), 'package.xml')).findtext('version')
    except (ImportError, LookupError, OSError, ValueError, ET.ParseError):
        version = None
    return (version or 'unknown').strip()


def version_text(prog: str, package: str) -> str:
    """The --version answer of executable `prog` of `package`: 'prog (package) version'."""
    return f'{prog} ({package}) {package_version(package)}\n'


def own_arguments(argv: list[str]) -> list[str]:
    """A node's own command-line arguments: those before --ros-args (the rest are ROS's)."""
    return argv[:argv.index('--ros-args')] if '--ros-args' in argv else list(argv)


def asks_only_version(argv: list[str]) -> bool:
    """True when a node's own arguments ask for --version and not for --help."""
    own = own_arguments(argv)
    return VERSION_FLAG in own and not any(a in HELP_FLAGS for a in own)


def quiet_main(target: str, interrupted: int = NODE_INTERRUPTED) -> Callable[[], int]:
    """A console-script function that imports `target` and returns `target.main()`.

    A SIGINT while importing, or a KeyboardInterrupt that `main` lets escape, ends the program with exit
    code `interrupted` and no traceback. `target` is a module name ('assist_policy.policy_node').
    """
    def exit_now(signum, frame) -> None:
        os._exit(interrupted)

    def main() -> int:
        if interrupted == NODE_INTERRUPTED and asks_only_version(sys.argv[1:]):
            # answered without importing the node (torch and rclpy are seconds of start-up)
            sys.stdout.write(version_text(os.path.basename(sys.argv[0]), target.split('.')[0]))
            return 0
        quiet = signal.getsignal(signal.SIGINT) is signal.default_int_handler   # not when SIGINT is ignored
        if quiet:
            signal.signal(signal.SIGINT, exit_now)
        try:
            module = importlib.import_module(target)
        finally:
            if quiet:
                signal.signal(signal.SIGINT, signal.default_int_handler)
        try:
            return module.main()
        except KeyboardInterrupt:
            return interrupted
    main.__doc__ = f'Run {target}.main(); a Ctrl-C during start-up exits {interrupted} without a traceback.'
    main.target = target
    main.interrupted = interrupted
    main.__qualname__ = main.__name__ = target.rsplit('.', 1)[-1]
    return main


def node_executables(packages: Iterable[str]) -> dict[str, tuple[str, str]]:
    """The workspace's one registry of nodes: executable -> (package, module defining it), read from each package's
    `entry_points` module (a quiet_main with NODE_INTERRUPTED is a node; tools exit TOOL_INTERRUPTED)."""
    nodes: dict[str, tuple[str, str]] = {}
    for pkg in packages:
        try:
            module = importlib.import_module(f'{pkg}.entry_points')
        except ModuleNotFoundError as exc:
            if exc.name != f'{pkg}.entry_points':
                raise
            continue                                   # a package without executables
        for name, value in vars(module).items():
            if callable(value) and getattr(value, 'interrupted', None) == NODE_INTERRUPTED:
                nodes[name] = (pkg, value.target)
    return nodes


def exit_now(code: int) -> typing.NoReturn:
    """End the process with `code` after flushing logging and the standard streams, without the interpreter's
    finalization (which would join threads and tear modules down: see ros_run.exit_process and
    assist_lab.cluster.exit_worker_died for why each needs that)."""
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)
