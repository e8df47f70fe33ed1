from setuptools import find_packages, setup

package_name = 'rfm_core'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'tests']),
    package_data={'rfm_core.matching': ['weights/*.npz'], 'rfm_core.detection': ['weights/*.json', 'weights/*.npz']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='rfm maintainers',
    maintainer_email='maintainers@rfm-slam.org',
    description='ROS-free core of rfm (Rooms from Motion): geometry, detection, matching, mapping, simulation, evaluation and I/O. Importable without ROS.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': [],
    },
)
