"""Build script for the assist_policy ament_python package (colcon and pip)."""
import os
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'assist_policy'
# The repository's models/ (ros2_ws/src/<package>/../../../models), relative to the working
# directory: colcon runs setup.py in the source dir, or in build/<package> for --symlink-install.
MODELS = os.path.relpath(os.path.join(os.path.dirname(os.path.realpath(__file__)), '..', '..', '..', 'models'))

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.py')),
        # shipped TD3 actors + cards (found by assist_common.shipped)
        ('share/' + PACKAGE + '/models', sorted(glob(os.path.join(MODELS, 'td3_*_actor.*')))),
    ],
    package_data={PACKAGE: ['data/*']},
    install_requires=['setuptools'],
    extras_require={'ray': ['ray==2.60.0']},   # evaluate --ray
    zip_safe=True,
    maintainer='Assisted landing maintainers',
    maintainer_email='maintainers@assist-landing.dev',
    description='Observation building, blending rule, TD3 assistant training and evaluation against simulated '
                'pilots, policy node',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'policy_node = assist_policy.entry_points:policy_node',
            'train_td3 = assist_policy.entry_points:train_td3',
            'evaluate = assist_policy.entry_points:evaluate',
            'evaluate_graph = assist_policy.entry_points:evaluate_graph',
            'compare_landings = assist_policy.entry_points:compare_landings',
            'bag_record = assist_policy.entry_points:bag_record',
            'bag_play = assist_policy.entry_points:bag_play',
            'replay_assist = assist_policy.entry_points:replay_assist',
            'plot_flight = assist_policy.entry_points:plot_flight',
        ],
    },
)
