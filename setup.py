"""Install coreg_ros as an ament_python package (colcon) or with pip."""

from glob import glob

from setuptools import find_packages, setup

package_name = 'coreg_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*', 'bench']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    python_requires='>=3.10',
    install_requires=['setuptools', 'numpy>=1.24', 'scipy>=1.9.2', 'rosbags>=0.10', 'PyYAML',
                      'rich>=13', 'threadpoolctl>=3'],
    extras_require={'test': ['pytest', 'hypothesis', 'ruff', 'pytest-xdist'],
                    'report': ['matplotlib'],
                    # --scheduler ADDRESS (coreg_ros.parallel): an existing Dask cluster
                    'dask': ['dask[distributed]>=2024.1'],
                    # plugins ament_flake8 / ament_pep257 need (their wheels do not pull them)
                    'lint': ['flake8', 'flake8-blind-except', 'flake8-builtins',
                             'flake8-class-newline', 'flake8-comprehensions', 'flake8-deprecated',
                             'flake8-docstrings', 'flake8-import-order', 'flake8-quotes',
                             'pydocstyle']},
    zip_safe=True,
    maintainer='coreg_ros developers',
    maintainer_email='dev@coreg-ros.invalid',
    description='Coregistration of two pose measurement devices (Ikits OLS/TLS) for ROS 2.',
    license='BSD-3-Clause',
    entry_points={
        'console_scripts': [
            'coreg = coreg_ros.entry:coreg',
            'coreg_node = coreg_ros.entry:coreg_node',
        ],
    },
)
