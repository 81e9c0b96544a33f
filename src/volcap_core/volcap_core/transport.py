"""Process set-up for moving 28 MB frame sets: the shipped Fast DDS profile and malloc tuning.

Call ``configure()`` before rclpy is initialised. An explicit ``FASTRTPS_DEFAULT_PROFILES_FILE`` in
the environment wins; ``VOLCAP_TRANSPORT=multihost`` selects the profile for a graph spread over
hosts (``fastdds_multihost.xml``: large UDP socket buffers, docs/multihost.md);
``VOLCAP_STOCK_DDS=1`` keeps Fast DDS's built-in transports (for comparisons such as
bench/transport.py).
"""
import ctypes
import os
from pathlib import Path

from .errors import BadInput

PROFILE = Path(__file__).with_name('config') / 'fastdds_volcap.xml'
MULTIHOST_PROFILE = Path(__file__).with_name('config') / 'fastdds_multihost.xml'
PROFILES = {'single': PROFILE, 'multihost': MULTIHOST_PROFILE}
PROFILE_ENV = 'FASTRTPS_DEFAULT_PROFILES_FILE'
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def configure(environ=os.environ) -> str | None:
    """Select the volcap Fast DDS profile and tune malloc; returns the profile in use, if any."""
    _tune_malloc()
    if environ.get('VOLCAP_STOCK_DDS') == '1':
        environ.pop(PROFILE_ENV, None)
        return None
    choice = environ.get('VOLCAP_TRANSPORT', 'single')
    if choice not in PROFILES:
        raise BadInput(f'VOLCAP_TRANSPORT must be one of {sorted(PROFILES)}, got {choice!r}')
    environ.setdefault(PROFILE_ENV, str(PROFILES[choice]))
    return environ[PROFILE_ENV]


def _tune_malloc():
    # Same effect as MALLOC_MMAP_THRESHOLD_/MALLOC_TRIM_THRESHOLD_ (5-17x faster large-message
    # handling, DESIGN.md), but also for processes started without those variables.
    try:
        libc = ctypes.CDLL('libc.so.6')
    except OSError:
        return
    libc.mallopt(_M_MMAP_THRESHOLD, 64 * 1024 * 1024)
    libc.mallopt(_M_TRIM_THRESHOLD, 256 * 1024 * 1024)
