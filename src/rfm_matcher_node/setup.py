from setuptools import find_packages, setup

package_name = 'rfm_matcher_node'

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
    description='rfm matcher node: keyframes and verified 4-DoF relative poses between them as a view graph (paper sections 3.2-3.4).',
    license='Apache-2.0',
    entry_points={
        'console_scripts': ['matcher = rfm_matcher_node.matcher_node:main'],
    },
)
