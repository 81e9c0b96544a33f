"""Shared fixtures. Each test process gets its own ROS domain and localhost-only discovery, so
parallel runs (and other sessions on the machine) never see each other's messages."""
import os
from pathlib import Path

import pytest

os.environ['ROS_DOMAIN_ID'] = str(1 + os.getpid() % 100)
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = REPO.parent / 'shared' / 'data'


@pytest.fixture(scope='session')
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f'shared data folder {SHARED_DATA} is absent')
    return SHARED_DATA


@pytest.fixture(scope='session')
def studio_bag(tmp_path_factory, shared_data):
    """One small 8-camera studio session (clean plate, 2 board poses, 2 capture frames)."""
    from volcap_driver.synth.session import synthesize
    from volcap_driver.synth.studio import SynthConfig
    out = tmp_path_factory.mktemp('studio') / 'bag'
    synthesize(out, SynthConfig(cameras=8, frames=2, board_poses=2, background_frames=1, seed=7), progress=False)
    return out


def _small_session(tmp_path_factory, name, **cfg):
    from volcap_driver.synth.session import synthesize
    from volcap_driver.synth.studio import SynthConfig
    out = tmp_path_factory.mktemp(name) / 'bag'
    synthesize(out, SynthConfig(frames=0, background_frames=0, seed=11, **cfg), progress=False)
    return out


@pytest.fixture(scope='session')
def calib_bag(tmp_path_factory, shared_data):
    """Two cameras on one stand; the first of two board poses faces them, the second turns away."""
    return _small_session(tmp_path_factory, 'calib2', cameras=2, board_poses=2)


@pytest.fixture(scope='session')
def calib_bag_blind_camera(tmp_path_factory, shared_data):
    """Three cameras; the one board pose faces the front stand, so cam2 (back stand) never sees it."""
    return _small_session(tmp_path_factory, 'calib3', cameras=3, board_poses=1)


@pytest.fixture
def ros_context():
    """An rclpy context for one test, shut down afterwards."""
    import rclpy

    from volcap_core import transport
    transport.configure()
    context = rclpy.Context()
    rclpy.init(context=context)
    yield context
    context.try_shutdown()


@pytest.fixture
def procs():
    """Node processes a test starts; each is stopped (SIGINT, then SIGKILL) afterwards."""
    from volcap_bringup.processes import stop
    started = []
    yield started
    for p in started:
        stop(p)
