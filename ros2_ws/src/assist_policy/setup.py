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
        # shipped TD3 actors + cards (found by assist_common.shipped)
        ('share/' + PACKAGE + '/models', sorted(glob(os.path.join(MODELS, 'td3_*_actor.*')))),
    ],
    package_data={PACKAGE: ['data/*']},
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='Assisted landing maintainers',
    maintainer_email='maintainers@assist-landing.dev',
    description='The assistant a vehicle runs: observation, the learned actor and the non-learned stages, policy_node',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'policy_node = assist_policy.entry_points:policy_node',
        ],
    },
)
