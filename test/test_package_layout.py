"""The install lays out what `ros2 run` needs (ament index, share/, lib/<pkg>/): `pip
install .` into the venv, or `colcon build` into a workspace's install/ (the prefix is
then found through the ament index of AMENT_PREFIX_PATH); package.xml's keys."""
import os
import subprocess
import sys

import pytest


def _find_prefix() -> str:
    """The package's install prefix: through the ament index where AMENT_PREFIX_PATH
    is set (a sourced colcon workspace or ROS install), else the venv's."""
    for p in os.environ.get('AMENT_PREFIX_PATH', '').split(os.pathsep):
        if p and os.path.exists(os.path.join(p, 'share', 'ament_index', 'resource_index',
                                             'packages', 'smpl_depth_ros')):
            return p
    return sys.prefix


PREFIX = _find_prefix()


@pytest.fixture(autouse=True)
def ament_prefix(monkeypatch):
    paths = os.environ.get('AMENT_PREFIX_PATH', '')
    if PREFIX not in paths.split(os.pathsep):
        monkeypatch.setenv('AMENT_PREFIX_PATH', os.pathsep.join(p for p in (PREFIX, paths) if p))


def test_ament_index_layout():
    from ament_index_python.packages import get_package_prefix, get_package_share_directory
    if not os.path.exists(os.path.join(PREFIX, 'share', 'ament_index', 'resource_index',
                                       'packages', 'smpl_depth_ros')):
        pytest.fail(f'smpl_depth_ros is not installed under {PREFIX}: run `make install` '
                    '(the README test command does it), or source a colcon workspace that '
                    'built it')
    assert get_package_prefix('smpl_depth_ros') == PREFIX
    share = get_package_share_directory('smpl_depth_ros')
    assert os.path.isfile(os.path.join(share, 'package.xml'))
    assert os.path.isfile(os.path.join(share, 'config', 'reconstructor.yaml'))
    for exe in ('reconstructor', 'process_bag', 'play_bag', 'synth_bag', 'oak_camera'):
        path = os.path.join(PREFIX, 'lib', 'smpl_depth_ros', exe)
        assert os.path.isfile(path) and os.access(path, os.X_OK), path


def test_lib_executable_runs_like_ros2_run():
    """What `ros2 run smpl_depth_ros synth_bag --help` would execute."""
    exe = os.path.join(PREFIX, 'lib', 'smpl_depth_ros', 'synth_bag')
    out = subprocess.run([sys.executable, exe, '--help'], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0 and '--frames' in out.stdout


def test_launchers_match_the_console_scripts():
    """resource/launchers/ (committed: no build writes into the source tree) holds one
    executable `ros2 run` launcher per console script of setup.py, calling it."""
    import ast
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    tree = ast.parse(open(os.path.join(repo, 'setup.py')).read())
    exes = next(ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign)
                and getattr(n.targets[0], 'id', '') == 'EXECUTABLES')
    folder = os.path.join(repo, 'resource', 'launchers')
    assert sorted(os.listdir(folder)) == sorted(exes)
    for name, target in exes.items():
        module, func = target.split(':')
        path = os.path.join(folder, name)
        text = open(path).read()
        assert os.access(path, os.X_OK) and text.startswith('#!/usr/bin/env python3')
        assert f'from {module} import {func}' in text and f'sys.exit({func}())' in text


# -- package.xml: real rosdep keys, one for every import ---------------------------------
REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
ROSDEP = os.path.join(os.path.dirname(REPO), 'shared', 'data', 'rosdep')
# Imported module -> its rosdep key (ROS packages are their own key).
MODULE_KEYS = {'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
               'PIL': 'python3-pil', 'tqdm': 'python3-tqdm', 'torch': 'python3-torch',
               'trimesh': 'python3-trimesh-pip', 'rosbags': 'python3-rosbags-pip',
               'depthai': 'python3-depthai-pip'}
NO_KEY = {'anny', 'safetensors', 'roma', 'embreex', 'threadpoolctl'}  # requirements-jazzy
OPTIONAL = {'compression', 'backports', 'lz4', 'pytest', 'ray'}  # guarded imports / tests only
ROS_MODULES = {'rclpy', 'rcl_interfaces', 'rosgraph_msgs', 'rosidl_runtime_py',
               'sensor_msgs', 'visualization_msgs', 'diagnostic_msgs', 'ament_index_python'}
# Message packages used by type name only ('geometry_msgs/msg/Point').
BY_NAME = {'std_msgs', 'geometry_msgs', 'builtin_interfaces'}


def _package_xml_deps() -> dict[str, set[str]]:
    import xml.etree.ElementTree as ET
    root = ET.parse(os.path.join(REPO, 'package.xml')).getroot()
    out: dict[str, set[str]] = {}
    for el in root:
        if el.tag.endswith('depend'):
            out.setdefault(el.tag, set()).add(el.text.strip())
    return out


def _third_party_imports() -> set[str]:
    import ast
    mods = set()
    for dirpath, _, files in os.walk(os.path.join(REPO, 'smpl_depth_ros')):
        for f in files:
            if f.endswith('.py'):
                tree = ast.parse(open(os.path.join(dirpath, f)).read())
                for n in ast.walk(tree):
                    if isinstance(n, ast.Import):
                        mods |= {a.name.split('.')[0] for a in n.names}
                    elif isinstance(n, ast.ImportFrom) and n.level == 0 and n.module:
                        mods.add(n.module.split('.')[0])
    return {m for m in mods if m not in sys.stdlib_module_names and m != 'smpl_depth_ros'}


def test_package_xml_declares_every_import_with_a_real_rosdep_key():
    deps = _package_xml_deps()
    run = deps.get('exec_depend', set())
    mods = _third_party_imports()
    unknown = mods - set(MODULE_KEYS) - NO_KEY - OPTIONAL - ROS_MODULES
    assert not unknown, f'imports without a mapping to a rosdep key: {unknown}'
    missing = {MODULE_KEYS.get(m, m) for m in mods - NO_KEY - OPTIONAL} - run
    assert not missing, f'package.xml lacks exec_depend {missing}'
    assert BY_NAME <= run
    with open(os.path.join(REPO, 'requirements-jazzy.txt')) as f:
        pinned = {line.split('==')[0].strip() for line in f
                  if line.strip() and not line.startswith('#')}
    assert NO_KEY <= pinned, NO_KEY - pinned
    assert 'python3-pytest' in deps.get('test_depend', set())
    if not os.path.isdir(ROSDEP):
        pytest.skip(f'no offline rosdep key list at {ROSDEP}')
    keys = set(open(os.path.join(ROSDEP, 'system_keys.txt')).read().split())
    keys |= set(open(os.path.join(ROSDEP, 'jazzy_packages.txt')).read().split())
    bad = {k for ks in deps.values() for k in ks} - keys
    assert not bad, f'not rosdep keys: {bad}'


def test_jazzy_requirements_pin_what_the_venv_pins():
    """requirements-jazzy.txt (a Jazzy install) pins every non-ROS requirement of the
    venv's requirements.txt at the same version, and no ROS wheel (nor the venv's
    `make test` tools: colcon, ruff)."""
    def pins(name):
        out = {}
        for line in open(os.path.join(REPO, name)):
            line = line.split('#')[0].strip()
            if line:
                pkg, ver = line.split('==')
                out[pkg.split('[')[0]] = ver
        return out
    venv, jazzy = pins('requirements.txt'), pins('requirements-jazzy.txt')
    assert not any(k.startswith('ros-') for k in jazzy)
    expected = {k: v for k, v in venv.items()
                if not k.startswith(('ros-', 'colcon-')) and k != 'ruff'}
    assert jazzy == expected
