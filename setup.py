import os
import stat
from glob import glob

from setuptools import find_packages, setup

package_name = 'dea_array_twin'

try:  # setuptools >= 70.1 ships bdist_wheel itself
    from setuptools.command.bdist_wheel import bdist_wheel as _bdist_wheel
except ImportError:
    try:
        from wheel.bdist_wheel import bdist_wheel as _bdist_wheel
    except ImportError:  # no wheel building here (e.g. colcon with an old setuptools)
        _bdist_wheel = None

# `ros2 run PKG EXE` looks only in <prefix>/lib/PKG/. colcon puts the console
# scripts there (setup.cfg [install] install_scripts), but a wheel's console
# scripts are written by pip into <prefix>/bin/ only, whatever setup.cfg says.
# So wheels (pip install .) also carry, as data, a launcher in lib/PKG/ that
# runs <prefix>/bin/EXE. colcon builds no wheel, so it never gets the launcher
# and its real script in lib/PKG/ is not overwritten.
console_scripts = {
    'dea-twin': 'dea_array_twin.cli:main',
    'twin_node': 'dea_array_twin.ros.node:main',
    'wave_controller': 'dea_array_twin.ros.wave_controller:main',
}

LAUNCHER = """#!/bin/sh
# Installed by pip so that `ros2 run {pkg} {exe}` finds the console script
# that pip wrote to <prefix>/bin/{exe}.
exec "$(dirname -- "$0")/../../bin/{exe}" "$@"
"""

cmdclass = {}
if _bdist_wheel is not None:
    class bdist_wheel(_bdist_wheel):
        """Build a wheel that also ships lib/<pkg>/<exe> launchers for `ros2 run`."""

        def run(self):
            base = os.path.join(self.get_finalized_command('build').build_base,
                                'ros2_run_launchers')
            os.makedirs(base, exist_ok=True)
            paths = []
            for exe in console_scripts:
                path = os.path.join(base, exe)
                with open(path, 'w') as f:
                    f.write(LAUNCHER.format(pkg=package_name, exe=exe))
                os.chmod(path, os.stat(path).st_mode | stat.S_IXUSR | stat.S_IXGRP | stat.S_IXOTH)
                paths.append(path)
            self.distribution.data_files.append(('lib/' + package_name, paths))
            super().run()

    cmdclass['bdist_wheel'] = bdist_wheel

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    # Non-ROS dependencies only. rclpy and the message packages come from the ROS
    # install (colcon) or from requirements-ros.txt (venv, tools/setup.sh); PyPI
    # ROS wheels must never be pulled in over a full ROS install. Every import that
    # is not inside a function is here (and in package.xml); mcap >= 1.5 for
    # Writer.flush, which closes a chunk on demand (the recorder's durability).
    # test/test_dependencies.py imports every module with only these installed.
    install_requires=['numpy', 'scipy', 'numba', 'gmsh', 'pyyaml', 'tqdm', 'mcap>=1.5',
                      'mcap-ros2-support'],
    # Optional, imported where used, with a message naming the extra when missing.
    extras_require={
        'test': ['pytest', 'pytest-timeout', 'import-linter>=2.1', 'ruff', 'rosbags'],
        'plot': ['matplotlib'],
        'cluster': ['dask[distributed]>=2024.1'],
    },
    zip_safe=True,
    maintainer='dea_array_twin developers',
    maintainer_email='maintainer@example.com',
    description='ROS 2 digital twin of a soft array of dielectric-elastomer transducers',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [f'{exe} = {target}' for exe, target in console_scripts.items()],
    },
    cmdclass=cmdclass,
)
