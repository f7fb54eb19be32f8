"""The workspace builds with colcon and installs every executable where `ros2 run` looks."""
import importlib
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SRC = REPO / 'ros2_ws' / 'src'
PACKAGES = ['assist_sim', 'assist_perception', 'assist_policy', 'assist_bridge', 'assist_station']
ENTRY = re.compile(r"'(\w+) = ([\w.]+):(\w+)'")


def console_scripts(pkg: str) -> dict[str, tuple[str, str]]:
    """name -> (module, function) from the package's setup.py."""
    text = (SRC / pkg / 'setup.py').read_text()
    return {m[0]: (m[1], m[2]) for m in ENTRY.findall(text)}


CONTRACT_SCRIPTS = {
    'assist_sim': {'sim_node', 'sim_pilot_node'},
    'assist_perception': {'encoder_node', 'make_dataset', 'train_cmvae'},
    'assist_policy': {'policy_node', 'train_td3', 'evaluate'},
    'assist_bridge': {'mavlink_bridge_node', 'teleop_keyboard'},
    'assist_station': {'pilot_station'},
}


@pytest.mark.parametrize('pkg', PACKAGES)
def test_package_metadata(pkg):
    root = SRC / pkg
    xml = ET.parse(root / 'package.xml').getroot()
    assert xml.get('format') == '3' and xml.findtext('name') == pkg
    assert xml.find('export/build_type').text == 'ament_python'
    deps = {e.text for e in xml.findall('exec_depend')}
    assert {'rclpy', 'launch_ros'} <= deps
    assert (root / 'resource' / pkg).exists()
    cfg = (root / 'setup.cfg').read_text()
    assert f'script_dir=$base/lib/{pkg}' in cfg and f'install_scripts=$base/lib/{pkg}' in cfg
    scripts = console_scripts(pkg)
    assert CONTRACT_SCRIPTS[pkg] <= set(scripts)


@pytest.mark.parametrize('pkg', PACKAGES)
def test_console_scripts_resolve_and_are_installed_in_the_venv(pkg):
    for name, (module, func) in console_scripts(pkg).items():
        mod = importlib.import_module(module)
        assert callable(getattr(mod, func)), f'{module}:{func}'
        assert (Path(sys.executable).parent / name).exists(), name


def test_colcon_build_installs_executables_where_ros2_run_looks(tmp_path):
    colcon = Path(sys.executable).parent / 'colcon'
    shutil.copytree(SRC, tmp_path / 'src', ignore=shutil.ignore_patterns('__pycache__', '*.egg-info'))
    proc = subprocess.run([str(colcon), 'build', '--build-base', 'build', '--install-base', 'install'],
                          cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    install = tmp_path / 'install'
    for pkg in PACKAGES:
        for name in console_scripts(pkg):
            exe = install / pkg / 'lib' / pkg / name
            assert exe.exists(), f'{exe} missing: ros2 run {pkg} {name} would fail'
        share = install / pkg / 'share'
        assert (share / 'ament_index' / 'resource_index' / 'packages' / pkg).exists()
        assert (share / pkg / 'package.xml').exists()
        for sub in ('config', 'launch'):
            src_files = sorted(p.name for p in (SRC / pkg / sub).glob('*') if p.suffix in ('.yaml', '.py', '.parm'))
            inst_files = sorted(p.name for p in (share / pkg / sub).glob('*'))
            assert src_files == inst_files, (pkg, sub)
