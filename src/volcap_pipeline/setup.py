from glob import glob

from setuptools import find_packages, setup

package_name = 'volcap_pipeline'

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
    description='The per-camera and rig pipelines (raw frames to cleaned, corrected views; frame sets to models) '
                'and the offline replay of a bag through them.',
    license='Apache-2.0',
    extras_require={'test': ['pytest']},
    entry_points={
        'console_scripts': [
            'camera_pipeline = volcap_pipeline.camera_pipeline_node:main',
        ],
    },
)
