"""Build script for the assist_common ament_python package (colcon and pip)."""
from setuptools import find_packages, setup

PACKAGE = 'assist_common'

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
    description='Shared plumbing of the assisted-landing packages: node parameters, QoS, diagnostics, node running, '
                'crash-safe writers, model lookup, launch helpers, frames and rotations, MAVLink I/O, settings rules, '
                'shared constants (no pybullet, no torch)',
    license='Apache-2.0',
    tests_require=['pytest'],
)
