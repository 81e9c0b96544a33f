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
