from setuptools import find_packages, setup

package_name = 'rfm_mapper_node'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'tests']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='rfm maintainers',
    maintainer_email='maintainers@rfm-slam.org',
    description='rfm mapper node: pose averaging, object tracks, box refinement, relocalization and map persistence (paper sections 3.5-3.6).',
    license='Apache-2.0',
    entry_points={
        'console_scripts': ['mapper = rfm_mapper_node.mapper_node:main'],
    },
)
