"""Build script for the assist_sim ament_python package (colcon and pip)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'assist_sim'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml') + glob('config/*.parm')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.py')),
    ],
    package_data={PACKAGE: ['data/*']},
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='Assisted landing maintainers',
    maintainer_email='maintainers@assist-landing.dev',
    description='pybullet landing world (scene generator, multirotor, velocity flight controller, turbulence, '
                'RGB-D camera, landing judge), simulated pilot and MAVLink vehicle stand-in',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'sim_node = assist_sim.entry_points:sim_node',
            'sim_pilot_node = assist_sim.entry_points:sim_pilot_node',
            'sitl_identify = assist_sim.entry_points:sitl_identify',
            'fit_guided = assist_sim.entry_points:fit_guided',
        ],
    },
)
