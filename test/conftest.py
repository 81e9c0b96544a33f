"""Shared fixtures. Each test process gets its own ROS domain and localhost-only discovery, so
parallel runs (and other sessions on the machine) never see each other's messages."""
import os
import time
from pathlib import Path

import pytest


def _domain_id() -> int:
    """A ROS domain of this test process's own (0-101 are safe on Linux). The workers of one
    parallel run (pytest-xdist ``gw0``, ``gw1``, ...; their parent is the run's controller) get
    neighbouring domains, so no two of them share one; a plain run takes one from its pid."""
    worker = os.environ.get('PYTEST_XDIST_WORKER', '')
    if worker.startswith('gw') and worker[2:].isdigit():
        return 1 + (os.getppid() % 25) * 4 + int(worker[2:]) % 4
    return 1 + os.getpid() % 100


os.environ['ROS_DOMAIN_ID'] = str(_domain_id())
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
if os.environ.get('PYTEST_XDIST_WORKER'):
    # `make test` runs a worker per core: OpenMP's pools (torch, Open3D, numba) sized to every
    # core in each worker and the nodes it starts oversubscribe them. One thread each: the two
    # torch-heavy files together 128 -> 108 s on 2 cores, the suite's pytest 13 min 22 s ->
    # 11 min 27 s on fresh clones (docs/benchmarks.md); set before any of them is imported.
    os.environ.setdefault('OMP_NUM_THREADS', '1')

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / 'shared' / 'data'
# Rendering or training these takes tens of seconds on 2 cores: tests that use them are `slow`.
SLOW_FIXTURES = {'browser', 'person_sequence', 'still_bag',
                 'studio_bag', 'calib_bag', 'calib_bag_good', 'calib_bag_blind_camera', 'k4a_bag', 'capture_bag', 'trained', 'install'}


def pytest_collection_modifyitems(items):
    for item in items:
        if SLOW_FIXTURES & set(getattr(item, 'fixturenames', ())):
            item.add_marker(pytest.mark.slow)


def require(condition: bool, reason: str) -> None:
    """A prerequisite (data, root, Chromium, namespaces): without it a test skips on a developer's
    machine, but in CI (``CI=true``) the missing prerequisite is a failure, never a silent skip."""
    if condition:
        return
    if os.environ.get('CI', '').lower() in ('true', '1', 'yes'):
        pytest.fail(f'CI lacks a prerequisite: {reason}', pytrace=False)
    pytest.skip(reason)


@pytest.fixture(scope='session')
def prerequisite():
    """``require`` for test modules (conftest is not importable under --import-mode=importlib)."""
    return require


@pytest.fixture(scope='session')
def shared_data() -> Path:
    require(SHARED_DATA.is_dir(), f'shared data folder {SHARED_DATA} is absent')
    return SHARED_DATA


def _rendered_once(tmp_path_factory, name, **cfg) -> Path:
    """A synthetic session rendered once per test run: the parallel workers (pytest-xdist) share
    the run's base folder, and the first to ask renders it while the others wait. Tests only
    read it (one that damages a bag damages a copy)."""
    from filelock import FileLock

    from volcap_studio.session import synthesize
    from volcap_studio.studio import SynthConfig
    root = tmp_path_factory.getbasetemp()
    if os.environ.get('PYTEST_XDIST_WORKER'):
        root = root.parent            # each worker's base folder sits in the run's
    folder = root / f'shared_{name}'
    with FileLock(str(root / f'shared_{name}.lock')):
        if not (folder / 'complete').exists():
            folder.mkdir(exist_ok=True)
            synthesize(folder / 'bag', SynthConfig(**cfg), progress=False, overwrite=True)
            (folder / 'complete').touch()
    return folder / 'bag'


@pytest.fixture(scope='session')
def studio_bag(tmp_path_factory, shared_data):
    """One small 8-camera studio session (clean plate, 2 board poses, 2 capture frames)."""
    return _rendered_once(tmp_path_factory, 'studio', cameras=8, frames=2, board_poses=2, background_frames=1,
                          seed=7)


@pytest.fixture(scope='session')
def still_bag(tmp_path_factory, shared_data):
    """Four cameras (two stands) on a subject that holds still (``--motion none``): 4 capture frames."""
    return _rendered_once(tmp_path_factory, 'still', cameras=4, frames=4, board_poses=0, background_frames=1,
                          seed=13, motion='none')


def _small_session(tmp_path_factory, name, **cfg):
    return _rendered_once(tmp_path_factory, name, frames=0, background_frames=0, seed=11, **cfg)


@pytest.fixture(scope='session')
def calib_bag(tmp_path_factory, shared_data):
    """Two cameras on one stand; the first of two board poses faces them, the second turns away."""
    return _small_session(tmp_path_factory, 'calib2', cameras=2, board_poses=2)


@pytest.fixture(scope='session')
def calib_bag_good(tmp_path_factory, shared_data):
    """Two cameras on one stand and 12 board poses: enough shared views for both to meet the target."""
    return _small_session(tmp_path_factory, 'calib12', cameras=2, board_poses=12)


@pytest.fixture(scope='session')
def calib_bag_blind_camera(tmp_path_factory, shared_data):
    """Three cameras; the one board pose faces the front stand, so cam2 (back stand) never sees it."""
    return _small_session(tmp_path_factory, 'calib3', cameras=3, board_poses=1)


@pytest.fixture(scope='session')
def k4a_bag(tmp_path_factory, shared_data):
    """The real Azure Kinect recording as a one-camera volcap bag."""
    from volcap_driver.k4a_import import import_k4a
    bag = tmp_path_factory.mktemp('k4a') / 'bag'
    import_k4a(shared_data / 'azure_kinect' / 'recording.mkv', bag, progress=False)
    return bag


@pytest.fixture(scope='session')
def gt_calibration():
    """A calibration with a synthetic bag's true camera poses and studio frame (and, optionally,
    one colour model for every camera)."""
    import numpy as np

    from volcap_core.calibration import Calibration, CameraCalibration, StudioFrame

    def make(gt, color: dict | None = None) -> Calibration:
        calibration = Calibration(gt.rig.names[0], f'{gt.rig.names[0]}_color_optical_frame',
                                  {c: CameraCalibration(gt.T_world_color(c), f'{c}_color_optical_frame', color=color)
                                   for c in gt.rig.names})
        calibration.studio = StudioFrame(np.linalg.inv(np.asarray(gt.doc['T_studio_world'], float)),
                                         details={'source': 'floor'})
        return calibration
    return make


@pytest.fixture
def graph():
    """The test's graph session, the one the commands use (``volcap_bringup.session.GraphSession``):
    transport, rclpy, one executor the test's probes spin in; everything shut down afterwards."""
    from volcap_bringup.session import GraphSession
    with GraphSession('volcap_test') as session:
        yield session


@pytest.fixture
def ros_context(graph):
    """The rclpy context of the test's graph session (for nodes a test builds itself)."""
    return graph.node.context


@pytest.fixture
def procs():
    """Node processes a test starts; all are stopped together (SIGINT, then SIGKILL) afterwards."""
    from volcap_bringup.processes import stop_all
    started = []
    yield started
    stop_all(started)


# Probes subscribe reliably (EVERY_FRAME): the player sends each frame once, and a best-effort
# reader on a loaded 2-core CI machine can lose a 2.7 MB frame (seen in CI).


class Probe:
    """Subscribes to topics in the test process and records (receive time, message); its node is
    hosted by the test's graph session and spins there."""

    def __init__(self, graph, subscriptions):
        import rclpy
        self.graph = graph
        self.node = graph.host(rclpy.create_node('probe', context=graph.node.context))
        self.got = {topic: [] for topic, _, _ in subscriptions}
        for topic, kind, profile in subscriptions:
            self.subscribe(topic, kind, profile)

    def subscribe(self, topic, kind, profile):
        self.got.setdefault(topic, [])
        self.node.create_subscription(kind, topic, lambda m, t=topic: self.got[t].append((time.monotonic(), m)),
                                      profile)

    def spin_until(self, done, timeout):
        return self.graph.spin_until(done, timeout)

    def assert_all_arrive(self, topics, timeout):
        assert self.spin_until(lambda: all(self.got[t] for t in topics), timeout=timeout), \
            f'no output on {[t for t in topics if not self.got[t]]}'

    def close(self):
        if self.node is not None:
            self.graph.release(self.node)
            self.node = None


@pytest.fixture
def probe_factory(graph):
    """Makes Probes in the test's graph session; each is closed afterwards."""
    probes = []

    def make(subscriptions):
        probes.append(Probe(graph, subscriptions))
        return probes[-1]
    yield make
    for p in probes:
        p.close()


@pytest.fixture
def play(procs):
    """Starts bag_player on a bag in its own process (stopped with the test's other nodes)."""
    from volcap_bringup.processes import start_node

    def start(bag, **params):
        procs.append(start_node('volcap_driver', 'bag_player', {'bag': str(bag), 'wait_for_subscribers': 20.0,
                                                                **params}))
        return procs[-1]
    return start


CHROMIUM = Path('/usr/bin/chromium')
# Debian's Chromium as root, headless, WebGL on SwiftShader (no GPU), no background traffic
# (this machine's network is closed).
CHROMIUM_ARGS = ['--no-sandbox', '--use-angle=swiftshader', '--enable-unsafe-swiftshader', '--no-first-run',
                 '--disable-background-networking', '--disable-component-update', '--disable-sync']


@pytest.fixture(scope='session')
def browser():
    """Headless Debian Chromium driven by Playwright (`make test` installs both)."""
    require(CHROMIUM.exists(), 'Debian chromium is not installed (make chromium)')
    from playwright.sync_api import sync_playwright
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield b
        b.close()


@pytest.fixture
def free_port() -> int:
    """A TCP port nobody listens on now (and the next one, for a WebSocket beside it)."""
    import socket
    for _ in range(50):
        with socket.socket() as a, socket.socket() as b:
            a.bind(('127.0.0.1', 0))
            port = a.getsockname()[1]
            try:
                b.bind(('127.0.0.1', port + 1))
            except OSError:
                continue
            return port
    raise RuntimeError('no two free neighbouring ports')


@pytest.fixture
def small_disk(tmp_path):
    """``small_disk(bytes)``: a folder on a tmpfs of that size, to fill up (needs root, as CI has)."""
    import subprocess
    mounts = []

    def make(size: int) -> Path:
        folder = tmp_path / f'disk{len(mounts)}'
        folder.mkdir()
        run = subprocess.run(['mount', '-t', 'tmpfs', '-o', f'size={size}', 'tmpfs', str(folder)],
                             capture_output=True, text=True)
        require(run.returncode == 0, f'cannot mount a small tmpfs here (needs root): {run.stderr.strip()}')
        mounts.append(folder)
        return folder
    yield make
    for folder in mounts:
        subprocess.run(['umount', '-l', str(folder)], capture_output=True)
