from glob import glob

from setuptools import find_packages, setup

package_name = 'volcap_filter'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    package_data={package_name: ['config/*']},
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob(package_name + '/config/*')),
    ],
    install_requires=['setuptools'],
    zip_safe=True,
    maintainer='volcap developers',
    maintainer_email='dev@volcap.invalid',
    description='Depth registration and cleaning, the depth_filter node.',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'depth_filter = volcap_filter.depth_filter_node:main',
        ],
    },
)
