"""Build script for the assist_bags ament_python package (colcon and pip)."""
from setuptools import find_packages, setup

PACKAGE = 'assist_bags'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml', 'README.md']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='Assisted landing maintainers',
    maintainer_email='maintainers@assist-landing.dev',
    description='rosbag2 bags of flights: record, play, replay the assistant offline, plot',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'bag_record = assist_bags.entry_points:bag_record',
            'bag_play = assist_bags.entry_points:bag_play',
            'replay_assist = assist_bags.entry_points:replay_assist',
            'plot_flight = assist_bags.entry_points:plot_flight',
        ],
    },
)
