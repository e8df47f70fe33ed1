from setuptools import find_packages, setup

package_name = 'rfm_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'tests']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/launch', ['launch/rfm.launch.py']),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='rfm maintainers',
    maintainer_email='maintainers@rfm-slam.org',
    description='The rfm command line (sim, play, record, run, eval, ...) and the launch file of the graph.',
    license='Apache-2.0',
    entry_points={
        'console_scripts': ['rfm = rfm_bringup.cli:main'],
    },
)
