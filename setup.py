"""ament_python package setup for smpl_depth_ros.

`pip install .` lays out the same tree colcon does: the ament index marker,
share/smpl_depth_ros/{package.xml,config}, and lib/smpl_depth_ros/<exe> wrappers so
`ros2 run smpl_depth_ros <exe>` works from a plain venv too.
"""
import glob
import os

from setuptools import find_packages, setup

package_name = 'smpl_depth_ros'

# Console scripts; each also gets a lib/<pkg>/<name> wrapper for `ros2 run`.
EXECUTABLES = {
    'reconstructor': 'smpl_depth_ros.ros.reconstructor_node:main',
    'oak_camera': 'smpl_depth_ros.ros.oak_camera_node:main',
    'reconstruct_oak': 'smpl_depth_ros.ros.oak_camera_node:main_with_reconstructor',
    'process_bag': 'smpl_depth_ros.offline:main',
    'play_bag': 'smpl_depth_ros.tools.play_bag:main',
    'synth_bag': 'smpl_depth_ros.tools.synth_bag:main',
    'render_panel': 'smpl_depth_ros.tools.render_panel:main',
    'train_correspondence': 'smpl_depth_ros.net.train:main',
    'evaluate': 'smpl_depth_ros.tools.evaluate:main',
    'benchmark': 'smpl_depth_ros.tools.benchmark:main',
    'sweep': 'smpl_depth_ros.tools.sweep:main',
    'evaluate_tracks': 'smpl_depth_ros.tools.evaluate_tracks:main',
}

# `ros2 run` launchers installed under lib/<package>/ (pip ignores setup.cfg's
# install_scripts), committed in resource/launchers/ so that no build writes into the
# source tree; test/test_package_layout.py checks they match EXECUTABLES.
LAUNCHERS = [os.path.join('resource', 'launchers', name) for name in EXECUTABLES]


setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['data/*.safetensors', 'data/*.pt', 'data/*.json', 'data/*.npz',
                                 'data/sample_bag/*', 'data/sample_bag/**/*']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', sorted(glob.glob('config/*'))),
        ('lib/' + package_name, LAUNCHERS),
    ],
    install_requires=['setuptools', 'numpy', 'scipy', 'torch', 'trimesh', 'rosbags',
                      'anny', 'safetensors', 'tqdm', 'pillow', 'roma', 'threadpoolctl'],
    # colcon test runs pytest; ray: process_bag --ray (optional)
    extras_require={'test': ['pytest', 'hypothesis'], 'ray': ['ray>=2.9']},
    zip_safe=False,
    maintainer='smpl_depth_ros maintainers',
    maintainer_email='maintainers@smpl-depth-ros.invalid',
    description='3D human body reconstruction from a single depth image, for ROS 2 Jazzy.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [f'{k} = {v}' for k, v in EXECUTABLES.items()],
    },
)
