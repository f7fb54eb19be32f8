"""`ros2 launch PACKAGE FILE [name:=value ...] [--show-args]` over the stand-in launch API (tests only).

Run with the environment of a sourced colcon install (AMENT_PREFIX_PATH, PYTHONPATH): the launch
file is looked up in share/PACKAGE (recursively, as ros2 launch does), `name:=value` pairs become
launch configurations before the description is visited, and the exit code is the launch
service's (0 after Ctrl-C; 1 when the launch itself failed).
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from ament_index_python.packages import get_package_share_directory
from launch import LaunchService
from launch._impl import log


def find_launch_file(package: str, name: str) -> Path:
    """The file called `name` under share/<package> (error when none or several)."""
    share = Path(get_package_share_directory(package))
    found = sorted(p for p in share.rglob(name) if p.is_file())
    if len(found) != 1:
        raise FileNotFoundError(f"file '{name}' was {'not found' if not found else 'found more than once'} "
                                f"in the share directory of package '{package}' [{share}]")
    return found[0]


def load_description(path: Path):
    """generate_launch_description() of a Python launch file."""
    spec = importlib.util.spec_from_file_location(path.stem.replace('.', '_'), path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def main(argv: list[str]) -> int:
    """CLI entry point."""
    show = '--show-args' in argv or '-s' in argv
    rest = [a for a in argv if a not in ('--show-args', '-s')]
    if len(rest) < 2:
        sys.stderr.write('usage: ros2launch.py PACKAGE FILE [name:=value ...] [--show-args]\n')
        return 2
    package, name, pairs = rest[0], rest[1], rest[2:]
    try:
        path = find_launch_file(package, name)
    except (LookupError, FileNotFoundError, OSError) as exc:
        sys.stderr.write(f'{exc}\n')
        return 1
    description = load_description(path)
    if show:
        print('Arguments (pass arguments as \'<name>:=<value>\'):\n')
        for arg in description.get_launch_arguments():
            print(f"    '{arg.name}':\n        {arg.description}")
            if arg.default_value is not None:
                default = ''.join(getattr(s, 'text', '<substitution>') for s in arg.default_value)
                print(f"        (default: '{default}')")
            print()
        return 0
    service = LaunchService(argv=pairs)
    for pair in pairs:
        key, sep, value = pair.partition(':=')
        if not sep:
            sys.stderr.write(f"malformed launch argument '{pair}', expected format '<name>:=<value>'\n")
            return 1
        service.context.launch_configurations[key] = value
    log('INFO', 'launch', f'launching {path}')
    service.include_launch_description(description)
    return service.run()


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
