"""The workspace builds with colcon and installs every executable where `ros2 run` looks."""
import importlib
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SRC = REPO / 'ros2_ws' / 'src'
PACKAGES = sorted(p.name for p in SRC.iterdir() if (p / 'package.xml').is_file())
ENTRY = re.compile(r"'(\w+) = ([\w.]+):(\w+)'")


def console_scripts(pkg: str) -> dict[str, tuple[str, str]]:
    """name -> (module, function) from the package's setup.py."""
    text = (SRC / pkg / 'setup.py').read_text()
    return {m[0]: (m[1], m[2]) for m in ENTRY.findall(text)}


CONTRACT_SCRIPTS = {
    'assist_common': set(),
    'assist_sim': {'sim_node', 'sim_pilot_node'},
    'assist_perception': {'encoder_node'},
    'assist_policy': {'policy_node'},
    'assist_bags': {'bag_record', 'bag_play', 'replay_assist', 'plot_flight'},
    'assist_lab': {'make_dataset', 'train_cmvae', 'evaluate_cmvae', 'train_td3', 'evaluate', 'evaluate_graph',
                   'compare_landings'},
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
    assert 'rclpy' in deps
    assert 'launch_ros' in deps or not (root / 'launch').exists()
    assert pkg == 'assist_common' or 'assist_common' in deps
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


@pytest.mark.parametrize('symlink', [False, True], ids=['plain', 'symlink'])
def test_colcon_build_installs_executables_where_ros2_run_looks(colcon_workspace, symlink):
    ws = colcon_workspace(symlink)
    install = ws.install
    for pkg in PACKAGES:
        for name in console_scripts(pkg):
            exe = install / pkg / 'lib' / pkg / name
            assert exe.exists(), f'{exe} missing: ros2 run {pkg} {name} would fail'
        share = install / pkg / 'share'
        assert (share / 'ament_index' / 'resource_index' / 'packages' / pkg).exists()
        assert (share / pkg / 'package.xml').exists()
        for sub in ('config', 'launch'):
            src_files = sorted(p.name for p in (SRC / pkg / sub).glob('*') if p.suffix in ('.yaml', '.py', '.parm'))
            # (__pycache__: what Python writes beside a launch file it loaded, e.g. in test_launch_files)
            inst_files = sorted(p.name for p in (share / pkg / sub).glob('*') if p.name != '__pycache__')
            assert src_files == inst_files, (pkg, sub)


SHIPPED = {'assist_policy': ['td3_end_to_end_actor.md', 'td3_end_to_end_actor.metrics.json', 'td3_end_to_end_actor.pt',
                             'td3_latent_actor.md', 'td3_latent_actor.metrics.json', 'td3_latent_actor.pt',
                             'td3_oracle_actor.md', 'td3_oracle_actor.metrics.json', 'td3_oracle_actor.pt'],
           'assist_perception': ['cmvae.md', 'cmvae.metrics.json', 'cmvae.pt', 'cmvae_interpolation.png']}


@pytest.mark.parametrize('symlink', [False, True], ids=['plain', 'symlink'])
def test_installed_nodes_find_the_shipped_models_in_share(colcon_workspace, symlink):
    """policy_node's and encoder_node's default models resolve to share/<pkg>/models of the install."""
    ws = colcon_workspace(symlink)
    for pkg, names in SHIPPED.items():
        models = ws.install / pkg / 'share' / pkg / 'models'
        assert sorted(p.name for p in models.iterdir()) == names
        for name in names:
            assert (models / name).read_bytes() == (REPO / 'models' / name).read_bytes(), name
    env = dict(ws.env)
    env.pop('ASSIST_MODELS_DIR', None)
    code = ('import assist_policy.policy_core as p, assist_perception.encoder_core as e\n'
            'print(p.__file__); print(p.default_model_path("latent")); print(e.default_model_path())')
    out = subprocess.run([sys.executable, '-c', code], env=env, cwd=ws.root, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    module, actor, cmvae = out.stdout.split()
    # the installed code (not the editable venv's checkout) found the installed models
    assert Path(module).is_relative_to(ws.ws), module
    assert actor == str(ws.install / 'assist_policy' / 'share' / 'assist_policy' / 'models' / 'td3_latent_actor.pt')
    assert cmvae == str(ws.install / 'assist_perception' / 'share' / 'assist_perception' / 'models' / 'cmvae.pt')
