"""Build script for the assist_station ament_python package (colcon and pip)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'assist_station'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.py')),
    ],
    package_data={PACKAGE: ['web/*']},
    install_requires=['setuptools'],
    zip_safe=False,
    maintainer='Assisted landing maintainers',
    maintainer_email='maintainers@assist-landing.dev',
    description='Base-station human interface: the browser pilot station and the user study',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'pilot_station = assist_station.entry_points:pilot_station',
            'simulate_study = assist_station.entry_points:simulate_study',
            'analyze_study = assist_station.entry_points:analyze_study',
        ],
    },
)
