"""Each package's package.xml says what its code imports and launches, both ways, and the vehicle's install pulls
no simulator and no lab dependency.

Read from the sources (no import is executed): every `import`/`from ... import` in a package's modules and launch
files (lazy ones inside functions too) and every `package='...'` a launch file starts a node from. An import of a
workspace package, a ROS package or a third-party module must be an `exec_depend` of the importing package (tests:
an `exec_depend` or a `test_depend`); an `exec_depend` must be imported or launched by the package's code.
"""
from __future__ import annotations

import ast
import re
import sys
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / 'ros2_ws' / 'src'
PACKAGES = sorted(p.name for p in SRC.iterdir() if (p / 'package.xml').is_file())

# Python module -> its rosdep key (the name package.xml uses). A third-party module missing here is an error, so a
# new dependency is declared on purpose.
ROSDEP = {'numpy': 'python3-numpy', 'cv2': 'python3-opencv', 'torch': 'python3-torch', 'yaml': 'python3-yaml',
          'scipy': 'python3-scipy', 'matplotlib': 'python3-matplotlib', 'pybullet': 'python3-pybullet-pip',
          'pybullet_utils': 'python3-pybullet-pip', 'pymavlink': 'python3-pymavlink-pip',
          'gymnasium': 'python3-gymnasium-pip', 'rosbags': 'python3-rosbags-pip',
          'PIL': 'python3-pil', 'aiohttp': 'python3-aiohttp', 'statsmodels': 'python3-statsmodels',
          'pandas': 'python3-pandas', 'tqdm': 'python3-tqdm', 'onnxruntime': 'python3-onnxruntime-pip',
          'onnx': 'python3-onnx-pip', 'pytest': 'python3-pytest', 'hypothesis': 'python3-hypothesis',
          'selenium': 'python3-selenium', 'psutil': 'python3-psutil'}
# Imported only behind an option, installed with pip's extra (`assist_lab[ray]`, requirements.txt); no rosdep key.
OPTIONAL = {'ray': {'assist_lab'}}
# ROS packages imported by their own name (message packages end in _msgs/_srvs/_interfaces).
ROS = {'rclpy', 'launch', 'launch_ros', 'ament_index_python', 'builtin_interfaces', 'rosidl_runtime_py'}
# Needed at run time though never imported by name: torch.onnx.export loads onnx.
RUNTIME_ONLY = {('assist_perception', 'python3-onnx-pip'): 'torch.onnx.export (the onnxruntime backend) needs it',
                ('assist_policy', 'python3-onnx-pip'): 'torch.onnx.export (actor_backend onnxruntime) needs it'}
# Started by a launch file only under a launch argument that a vehicle does not use; not a dependency.
OPTIONAL_LAUNCH = {('assist_bridge', 'assist_sim'): 'onboard.launch.py camera:=sim tries the split without hardware',
                   ('assist_bridge', 'realsense2_camera'): "the camera's driver, from the ROS distribution"}
# What a vehicle installs, and what none of it may pull (directly or through another package).
VEHICLE = ('assist_common', 'assist_perception', 'assist_policy', 'assist_bridge')
NOT_ON_VEHICLE = {'assist_sim', 'assist_lab', 'assist_station', 'python3-pybullet-pip', 'python3-gymnasium-pip',
                  'python3-matplotlib', 'ray'}


@dataclass
class Manifest:
    """One package: its declared dependencies and what its code uses, each with the file that uses it."""
    name: str
    exec_depend: set[str]
    test_depend: set[str]
    imports: dict[str, set[str]] = field(default_factory=dict)        # key -> files (package modules, launch)
    launches: dict[str, set[str]] = field(default_factory=dict)       # package -> launch files
    test_imports: dict[str, set[str]] = field(default_factory=dict)   # key -> test files


def dependency_key(module: str, importer: str) -> str | None:
    """The package.xml name of a top-level module (None: the standard library or the importer itself)."""
    if module in sys.stdlib_module_names or module == '__future__' or module == importer:
        return None
    if module.startswith('assist_') or module in ROS or re.search(r'_(msgs|srvs|interfaces)$', module):
        return module
    if module in OPTIONAL:
        return module
    if module in ROSDEP:
        return ROSDEP[module]
    raise KeyError(module)


def imported_modules(path: Path) -> set[str]:
    """Top-level names of every absolute import in a Python file."""
    tree = ast.parse(path.read_text(encoding='utf-8'), str(path))
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name.split('.')[0] for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.add(node.module.split('.')[0])
    return out


def launched_packages(path: Path) -> set[str]:
    """Packages a launch file starts nodes from (`package='...'`)."""
    tree = ast.parse(path.read_text(encoding='utf-8'), str(path))
    return {kw.value.value for node in ast.walk(tree) if isinstance(node, ast.Call) for kw in node.keywords
            if kw.arg == 'package' and isinstance(kw.value, ast.Constant) and isinstance(kw.value.value, str)}


def read_manifest(pkg: str) -> Manifest:
    """Parse ros2_ws/src/<pkg>: package.xml and the imports of its code, launch files and tests."""
    root = ET.parse(SRC / pkg / 'package.xml').getroot()
    m = Manifest(pkg, {e.text.strip() for e in root.iter('exec_depend')},
                 {e.text.strip() for e in root.iter('test_depend')})
    code = sorted((SRC / pkg / pkg).rglob('*.py')) + sorted((SRC / pkg / 'launch').glob('*.py'))
    for target, files in ((m.imports, code), (m.test_imports, sorted((SRC / pkg / 'test').rglob('*.py')))):
        for f in files:
            rel = str(f.relative_to(SRC))
            for mod in imported_modules(f):
                try:
                    key = dependency_key(mod, pkg)
                except KeyError:
                    pytest.fail(f'{pkg}: {rel} imports {mod!r}, which has no rosdep key in ROSDEP '
                                f'(tests/test_package_manifests.py): declare it there and in package.xml')
                if key:
                    target.setdefault(key, set()).add(rel)
    for f in sorted((SRC / pkg / 'launch').glob('*.py')):
        for p in launched_packages(f) - {pkg}:
            m.launches.setdefault(p, set()).add(str(f.relative_to(SRC)))
    return m


MANIFESTS = {p: read_manifest(p) for p in PACKAGES}


def missing_from_manifest(m: Manifest) -> list[str]:
    """One line per import or launch the package.xml does not declare: the package, the import, the file."""
    out = [f'{m.name}: {sorted(files)[0]} imports {key}, which is not an exec_depend in {m.name}/package.xml'
           for key, files in sorted(m.imports.items())
           if key not in m.exec_depend and not (key in OPTIONAL and m.name in OPTIONAL[key])]
    out += [f'{m.name}: {sorted(files)[0]} launches a node of {key}, which is not an exec_depend in '
            f'{m.name}/package.xml' for key, files in sorted(m.launches.items())
            if key not in m.exec_depend and (m.name, key) not in OPTIONAL_LAUNCH]
    out += [f'{m.name}: the test {sorted(files)[0]} imports {key}, which is neither an exec_depend nor a test_depend '
            f'in {m.name}/package.xml' for key, files in sorted(m.test_imports.items())
            if key not in m.exec_depend | m.test_depend and key not in OPTIONAL]
    return out


def unused_in_manifest(m: Manifest) -> list[str]:
    """One line per exec_depend that no module or launch file of the package uses."""
    return [f'{m.name}: package.xml declares exec_depend {dep}, but no module or launch file of {m.name} imports or '
            f'launches it' for dep in sorted(m.exec_depend)
            if dep not in m.imports and dep not in m.launches and (m.name, dep) not in RUNTIME_ONLY]


def install_closure(roots: tuple[str, ...]) -> dict[str, str]:
    """Every dependency an install of `roots` pulls (through workspace packages' exec_depend) -> who pulls it."""
    pulled: dict[str, str] = {}
    stack = [(r, 'installed') for r in roots]
    while stack:
        name, by = stack.pop()
        if name in pulled:
            continue
        pulled[name] = by
        if name in MANIFESTS:
            stack += [(d, name) for d in sorted(MANIFESTS[name].exec_depend)]
    return pulled


@pytest.mark.parametrize('pkg', PACKAGES)
def test_package_xml_declares_every_import_and_launch(pkg: str):
    assert missing_from_manifest(MANIFESTS[pkg]) == []


@pytest.mark.parametrize('pkg', PACKAGES)
def test_package_xml_declares_nothing_the_package_does_not_use(pkg: str):
    assert unused_in_manifest(MANIFESTS[pkg]) == []


def test_the_vehicles_install_pulls_no_simulator_and_no_lab():
    pulled = install_closure(VEHICLE)
    bad = {dep: by for dep, by in pulled.items() if dep in NOT_ON_VEHICLE}
    assert bad == {}, '; '.join(f'{dep} pulled by {by}' for dep, by in sorted(bad.items()))
    for key in OPTIONAL:        # optional modules stay out of the vehicle's packages' code too
        assert not {p for p in VEHICLE if key in MANIFESTS[p].imports}, key
    assert {'assist_common', 'python3-torch', 'rclpy'} <= set(pulled)       # the closure is walked


def test_assist_common_is_the_base_and_the_sim_imports_nothing_above_it():
    common = MANIFESTS['assist_common'].imports
    assert not {k for k in common if k.startswith('assist_')}
    assert not {'python3-pybullet-pip', 'python3-torch', 'python3-matplotlib'} & set(common)
    assert {k for k in MANIFESTS['assist_sim'].imports if k.startswith('assist_')} == {'assist_common'}


def test_the_check_names_the_package_the_import_and_the_file():
    m = Manifest('assist_policy', {'rclpy', 'python3-yaml'}, set(),
                 imports={'rclpy': {'assist_policy/assist_policy/policy_node.py'},
                          'python3-pybullet-pip': {'assist_policy/assist_policy/x.py'}},
                 launches={'assist_sim': {'assist_policy/launch/a.launch.py'}})
    assert missing_from_manifest(m) == [
        'assist_policy: assist_policy/assist_policy/x.py imports python3-pybullet-pip, which is not an exec_depend '
        'in assist_policy/package.xml',
        'assist_policy: assist_policy/launch/a.launch.py launches a node of assist_sim, which is not an exec_depend '
        'in assist_policy/package.xml']
    assert unused_in_manifest(m) == ['assist_policy: package.xml declares exec_depend python3-yaml, but no module '
                                     'or launch file of assist_policy imports or launches it']
    with pytest.raises(KeyError):
        dependency_key('some_unknown_module', 'assist_policy')
    assert dependency_key('os', 'assist_policy') is None and dependency_key('std_msgs', 'x') == 'std_msgs'
