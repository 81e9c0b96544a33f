from glob import glob

from setuptools import find_packages, setup

package_name = 'volcap_bringup'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['config/*']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob(package_name + '/config/*')),
        ('share/' + package_name + '/launch', glob('launch/*.launch.py')),
        ('lib/' + package_name, ['scripts/live_controller']),     # for `ros2 run`
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='volcap developers',
    maintainer_email='dev@volcap.invalid',
    description='The volcap command line, volcap run (the whole graph on a bag), the graph description and the launch file.',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={
        # The volcap command line; installed to bin/ (setup.cfg), which colcon puts on PATH.
        'console_scripts': [
            'volcap = volcap_bringup.cli:main',
        ],
    },
)
