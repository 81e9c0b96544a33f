from glob import glob

from setuptools import find_packages, setup

package_name = 'volcap_color'

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
    description='Per-camera colour correction (the color_corrector node), chart-free and neural harmonisation.',
    license='Apache-2.0',
    # torch only for volcap harmonise (training); the node applies the exported LUTs without it
    extras_require={'test': ['pytest'], 'neural': ['torch']},
    entry_points={
        'console_scripts': [
            'color_corrector = volcap_color.color_corrector_node:main',
        ],
    },
)
