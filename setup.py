"""ament_python package snn_rendezvous; installable by colcon and by pip alike."""

import os
import sys
from glob import glob

from setuptools import find_packages, setup

# The executables are listed once, in scenario_nodes/registry.py (standard library only), read
# from this source tree: nothing of the package is installed yet.
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from scenario_nodes.registry import executables  # noqa: E402

PACKAGE = 'snn_rendezvous'
EXECUTABLES = executables()

data_files = [
    ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
    (f'share/{PACKAGE}', ['package.xml']),
    (f'share/{PACKAGE}/launch', glob('launch/*.launch.py')),
    (f'share/{PACKAGE}/config', glob('config/*.yaml')),
    (f'share/{PACKAGE}/config/campaigns', glob('config/campaigns/*.yaml')),
    # the live view's RViz config and Foxglove layout
    (f'share/{PACKAGE}/config', glob('config/*.rviz') + glob('config/*.json')),
    # the Fast DDS profile the demo and the launch file point Fast DDS at (docs/decisions.md, 38)
    (f'share/{PACKAGE}/config', glob('config/*.xml')),
    (f'share/{PACKAGE}/rosdep', glob('rosdep/*.yaml')),
]
# `ros2 run` looks for executables in <prefix>/lib/<package>. colcon puts the console scripts
# there (setup.cfg install_scripts); pip puts them in <prefix>/bin, so a pip install also gets
# small wrappers in lib/<package> that exec the console script in ../../bin.
if not os.environ.get('COLCON'):
    data_files.append((f'lib/{PACKAGE}', sorted(glob('wrappers/*'))))

setup(
    name=PACKAGE,
    version='0.1.0',
    description='Spiking-network EKF/EMSIF state estimators in a closed-loop CW rendezvous '
                'GNC pipeline for ROS 2 Jazzy',
    long_description=open('README.md', encoding='utf-8').read() if os.path.exists('README.md') else '',
    long_description_content_type='text/markdown',
    license='Apache-2.0',
    packages=find_packages(exclude=['test', 'test.*']),
    data_files=data_files,
    python_requires='>=3.10',
    install_requires=[
        'setuptools',
        # brian2 2.9.0 (the independent simulator of the neuromorphic check) does not import
        # with numpy 2.3+ (ndarray.ptp); numba 0.68 supports 2.2
        'numpy>=1.24,<2.3',
        'scipy>=1.10',
        'control>=0.10',
        'numba>=0.58',
        'matplotlib>=3.6',
        'rosbags>=0.10',
        'PyYAML>=6',
    ],
    extras_require={
        # the Basilisk truth plant (issue: high-fidelity truth); pinned, its API moves
        'basilisk': ['bsk==2.12.1'],
        # Monte-Carlo campaigns on Dask, results as Parquet, the interactive page (plotly, pinned)
        'campaign': ['dask[distributed]>=2024.1', 'pyarrow>=14', 'plotly==7.1.0'],
        # NIR export of the networks and the independent Brian2 simulation of them
        'neuromorphic': ['nir>=1.0', 'brian2==2.9.0'],
        # the live view over Foxglove's WebSocket protocol; pinned, its API moves
        'live': ['foxglove-sdk==0.30.3'],
        # websockets and protobuf: the tests' Foxglove client decodes what the live view sends
        'test': ['pytest>=7', 'pytest-xdist>=3', 'hypothesis>=6', 'ruff>=0.6', 'websockets==17.4',
                 'protobuf>=4.21', 'filterpy>=1.4.5'],
    },
    zip_safe=True,
    maintainer='snn_rendezvous maintainers',
    maintainer_email='maintainers@users.noreply.h-seed-73572919.example',
    entry_points={'console_scripts': [f'{name} = {target}' for name, target in EXECUTABLES.items()]},
)
