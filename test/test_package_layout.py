"""`pip install .` lays out what `ros2 run` needs (ament index, share/, lib/<pkg>/)."""
import os
import subprocess
import sys

import pytest

PREFIX = sys.prefix


@pytest.fixture(autouse=True)
def ament_prefix(monkeypatch):
    monkeypatch.setenv('AMENT_PREFIX_PATH', PREFIX)


def test_ament_index_layout():
    from ament_index_python.packages import get_package_prefix, get_package_share_directory
    if not os.path.exists(os.path.join(PREFIX, 'share', 'ament_index', 'resource_index',
                                       'packages', 'smpl_depth_ros')):
        pytest.fail('smpl_depth_ros is not installed into the venv: run `make install` '
                    '(the README test command does it)')
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
