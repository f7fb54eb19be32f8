"""Build script for the assist_bridge ament_python package (colcon and pip)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'assist_bridge'

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
    description='MAVLink bridge to ArduPilot (pymavlink) and keyboard teleop',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'mavlink_bridge_node = assist_bridge.entry_points:mavlink_bridge_node',
            'teleop_keyboard = assist_bridge.entry_points:teleop_keyboard',
            'landing_runner = assist_bridge.entry_points:landing_runner',
            'image_relay = assist_bridge.entry_points:image_relay',
            'image_decoder = assist_bridge.entry_points:image_decoder',
        ],
    },
)
