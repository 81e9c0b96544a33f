"""Packaging truth: every package.xml declares what its package imports (volcap packages, ROS
interfaces and Python libraries under their rosdep keys)."""
import ast
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / 'src'


KEYS = {
    'numpy': 'python3-numpy', 'cv2': 'python3-opencv', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
    'open3d': 'python3-open3d', 'numba': 'python3-numba', 'matplotlib': 'python3-matplotlib',
    'torch': 'python3-torch', 'tqdm': 'python3-tqdm', 'colour': 'python3-colour-science-pip',
    'rosbags': 'python3-rosbags-pip', 'mcap': 'python3-mcap-pip', 'mcap_ros2': 'python3-mcap-ros2-support-pip',
    'pointcloud2': 'python3-pointcloud2-pip', 'av': 'python3-av', 'DracoPy': 'python3-dracopy-pip',
    'meshoptimizer': 'python3-meshoptimizer-pip', 'websockets': 'python3-websockets', 'rerun': 'python3-rerun-sdk-pip',
    'isal': 'python3-isal-pip', 'zstandard': 'python3-zstandard',
    'rich': 'python3-rich', 'psutil': 'python3-psutil', 'rclpy': 'rclpy', 'launch': 'launch', 'launch_ros': 'launch_ros',
}
ROS_MSG = {'sensor_msgs', 'std_msgs', 'std_srvs', 'geometry_msgs', 'visualization_msgs', 'diagnostic_msgs',
           'builtin_interfaces', 'rcl_interfaces', 'tf2_msgs'}


def imported_roots(package_dir: Path) -> set[str]:
    roots = set()
    for f in package_dir.rglob('*.py'):
        if f.name == 'setup.py':
            continue
        for node in ast.walk(ast.parse(f.read_text())):
            if isinstance(node, ast.Import):
                roots |= {a.name.split('.')[0] for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                roots.add(node.module.split('.')[0])
    return roots


def required_keys(package_dir: Path) -> set[str]:
    name = package_dir.name
    keys = set()
    for root in imported_roots(package_dir):
        if root == name or root in sys.stdlib_module_names or root == '__future__':
            continue
        if root.startswith('volcap_') or root in ROS_MSG:
            keys.add(root)
        elif root in KEYS:
            keys.add(KEYS[root])
        else:
            keys.add(f'?{root}')
    return keys

# Run as nodes by volcap run and the launch file, not imported.
STARTED = {'volcap_bringup': {'volcap_filter', 'volcap_calib', 'volcap_color', 'volcap_fusion', 'volcap_driver',
                              'volcap_studio'}}


@pytest.mark.parametrize('package', sorted(p.name for p in SRC.glob('volcap_*')))
def test_package_xml_declares_what_the_package_imports(package):
    root = ET.parse(SRC / package / 'package.xml').getroot()
    assert root.get('format') == '3' and root.findtext('name') == package
    declared = {e.text for e in root.findall('exec_depend')}
    missing = required_keys(SRC / package) - declared
    assert not missing, f'{package}/package.xml lacks exec_depend {sorted(missing)}'
    volcap = {d for d in declared if d.startswith('volcap_')}
    unused = volcap - required_keys(SRC / package) - STARTED.get(package, set())
    assert not unused, f'{package}/package.xml declares volcap packages it does not use: {sorted(unused)}'
