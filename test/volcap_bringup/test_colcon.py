"""`colcon build` of src/ as on a rig, and every declared executable found and started where
`ros2 run <pkg> <exe>` looks for it (install/<pkg>/lib/<pkg>/<exe>)."""
import configparser
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGES = sorted(p.name for p in (REPO / 'src').iterdir() if (p / 'package.xml').exists())


def declared_executables():
    out = []
    for pkg in PACKAGES:
        text = (REPO / 'src' / pkg / 'setup.py').read_text()
        out += [(pkg, name) for name in re.findall(r"'(\w+) = [\w.]+:main'", text) if pkg != 'volcap_bringup']
    return out


@pytest.fixture(scope='module')
def install(tmp_path_factory):
    if shutil.which('colcon', path=str(Path(sys.executable).parent)) is None:
        pytest.fail('colcon is not installed in the venv (make venv installs colcon-core and colcon-ros)')
    base = tmp_path_factory.mktemp('colcon')
    colcon = str(Path(sys.executable).parent / 'colcon')
    run = subprocess.run([colcon, '--log-base', str(base / 'log'), 'build', '--base-paths', str(REPO / 'src'),
                          '--build-base', str(base / 'build'), '--install-base', str(base / 'install'),
                          '--event-handlers', 'console_direct-'],
                         cwd=base, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert run.stdout.count('Finished <<<') == len(PACKAGES), run.stdout
    return base / 'install'


def test_every_package_is_ament_python_format_3():
    assert PACKAGES == ['volcap_bringup', 'volcap_calib', 'volcap_color', 'volcap_core', 'volcap_driver',
                        'volcap_eval', 'volcap_filter', 'volcap_fusion', 'volcap_pipeline', 'volcap_studio']
    for pkg in PACKAGES:
        xml = (REPO / 'src' / pkg / 'package.xml').read_text()
        assert '<package format="3">' in xml and '<build_type>ament_python</build_type>' in xml
        cfg = configparser.ConfigParser()
        cfg.read(REPO / 'src' / pkg / 'setup.cfg')
        # node executables where `ros2 run` looks; bringup's `volcap` command on PATH
        assert cfg['install']['install_scripts'] == ('$base/bin' if pkg == 'volcap_bringup' else f'$base/lib/{pkg}')
        assert re.search(r"extras_require=\{'test': \['pytest'\][,}]", (REPO / 'src' / pkg / 'setup.py').read_text())


def test_install_layout(install):
    for pkg in PACKAGES:
        assert (install / pkg / 'share' / 'ament_index' / 'resource_index' / 'packages' / pkg).exists()
        assert (install / pkg / 'share' / pkg / 'package.xml').exists()
    assert list((install / 'volcap_core').rglob('config/fastdds_volcap.xml'))
    assert list((install / 'volcap_calib').rglob('config/board.yaml'))
    assert (install / 'volcap_bringup' / 'share' / 'volcap_bringup' / 'launch' / 'volcap.launch.py').exists()


def test_the_volcap_command_is_installed_on_the_path(install):
    env = dict(os.environ)
    env['AMENT_PREFIX_PATH'] = sys.prefix
    run = subprocess.run(['bash', '-c', f'. "{install}/setup.sh" && command -v volcap && volcap --help'], env=env,
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    assert run.stdout.splitlines()[0] == str(install / 'volcap_bringup' / 'bin' / 'volcap')
    assert 'calibrate' in run.stdout and 'eval' in run.stdout


def run_installed(install, pkg, exe, params, data):
    env = dict(os.environ)
    env['AMENT_PREFIX_PATH'] = sys.prefix
    env['VOLCAP_DATA'] = str(data)
    script = (f'. "{install}/setup.sh" && exec "{install}/{pkg}/lib/{pkg}/{exe}" --ros-args '
              + ' '.join(f'-p {k}:={v}' for k, v in params.items()))
    return subprocess.Popen(['bash', '-c', script], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, start_new_session=True)


@pytest.mark.ros
@pytest.mark.parametrize('pkg, exe', declared_executables())
def test_executables_start_from_the_install_space(install, pkg, exe, studio_bag, tmp_path, shared_data):
    path = install / pkg / 'lib' / pkg / exe
    assert path.exists() and os.access(path, os.X_OK)
    params = {'bag_player': {'bag': str(studio_bag), 'as_fast_as_possible': 'true', 'topics': "['volcap/rig']"},
              'recorder': {'out': str(tmp_path / 'rec')},
              'synthetic_rig': {'cameras': 1, 'frames': 1, 'fps': 5.0},
              'depth_filter': {'camera': 'cam0'},
              'calibration_service': {'output': str(tmp_path / 'calibration.yaml')},
              'color_corrector': {'camera': 'cam0'},
              'camera_pipeline': {'camera': 'cam0'},
              'tsdf_fusion': {'voxel_size': 0.01}}[exe]
    proc = run_installed(install, pkg, exe, params, shared_data)
    try:
        lines = []
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if f'{exe} started' in line:
                break
        assert any(f'{exe} started' in line for line in lines), ''.join(lines)
        if exe == 'bag_player':
            assert proc.wait(60) == 0
        else:
            os.killpg(proc.pid, signal.SIGINT)
            assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
