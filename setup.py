from glob import glob

from setuptools import find_packages, setup

package_name = 'kpi_calib_ros'

setup(
    name=package_name,
    version='0.2.0',
    packages=find_packages(exclude=['test', 'test.*', 'bench', 'bench.*']),
    package_data={package_name: ['data/robots/*.urdf', 'data/cells/*.yaml']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='kpi_calib_ros maintainers',
    maintainer_email='maintainers@kpi-calib.invalid',
    description='KPI-based laser-tracker calibration of industrial manipulators',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'kpi-calib = kpi_calib_ros.cli:main',
            'kpi_calib_node = kpi_calib_ros.ros.node:main',
        ],
    },
)
