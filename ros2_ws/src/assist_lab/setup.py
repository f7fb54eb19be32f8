"""Build script for the assist_lab ament_python package (colcon and pip)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = 'assist_lab'

setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + PACKAGE]),
        ('share/' + PACKAGE, ['package.xml', 'README.md']),
        ('share/' + PACKAGE + '/config', glob('config/*.yaml')),
        ('share/' + PACKAGE + '/launch', glob('launch/*.launch.py')),
    ],
    install_requires=['setuptools'],
    extras_require={'ray': ['ray==2.60.0']},   # evaluate --ray, train_td3 --ray
    zip_safe=True,
    maintainer='Assisted landing maintainers',
    maintainer_email='maintainers@assist-landing.dev',
    description='The research lab: the simulated landing env, TD3 and CM-VAE training, evaluation against '
                'simulated pilots (in process and through the node graph), comparison, simulated-graph launches',
    license='Apache-2.0',
    tests_require=['pytest'],
    entry_points={
        'console_scripts': [
            'train_td3 = assist_lab.entry_points:train_td3',
            'evaluate = assist_lab.entry_points:evaluate',
            'evaluate_graph = assist_lab.entry_points:evaluate_graph',
            'compare_landings = assist_lab.entry_points:compare_landings',
            'make_dataset = assist_lab.entry_points:make_dataset',
            'train_cmvae = assist_lab.entry_points:train_cmvae',
            'evaluate_cmvae = assist_lab.entry_points:evaluate_cmvae',
        ],
    },
)
