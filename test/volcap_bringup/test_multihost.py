"""The graph across two hosts: network namespaces joined by a veth link (made here, as root), a
bag player and a colour corrector on the capture host, a subscriber on the fusion host, Fast DDS
over UDP with the shipped multi-host profile; the link goes down for 2 s and the stream resumes."""
import json
import os
import shutil
import subprocess
import sys
import time

import pytest

from volcap_bringup.processes import start_node, stop
from volcap_core import topics

pytestmark = [pytest.mark.ros, pytest.mark.slow]

RECEIVER = '''
import json, sys, time, rclpy
from sensor_msgs.msg import Image
from volcap_core import qos, transport
from volcap_core.cdr import cdr_stamp_ns
transport.configure()
rclpy.init()
node = rclpy.create_node('fusion_host_probe')
got = []
node.create_subscription(Image, sys.argv[1], lambda d: got.append((time.time_ns(), cdr_stamp_ns(d))), qos.CAMERA,
                         raw=True)
end = time.monotonic() + float(sys.argv[2])
while time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
print(json.dumps(got))
'''


@pytest.fixture
def hosts(prerequisite):
    """Two network namespaces (capture, fusion) joined by a veth link."""
    prerequisite(os.geteuid() == 0 and shutil.which('ip') is not None, 'network namespaces need root and iproute2')
    tag = str(os.getpid() % 100000)
    names = {'capture': f'vc_cap{tag}', 'fusion': f'vc_fus{tag}'}
    links = {'capture': (f'vc{tag}a', '10.78.0.1'), 'fusion': (f'vc{tag}b', '10.78.0.2')}

    def ip(*args):
        subprocess.run(['ip', *args], check=True, capture_output=True)
    try:
        for ns in names.values():
            ip('netns', 'add', ns)
        ip('link', 'add', links['capture'][0], 'type', 'veth', 'peer', 'name', links['fusion'][0])
        for host, ns in names.items():
            iface, address = links[host]
            ip('link', 'set', iface, 'netns', ns)
            ip('-n', ns, 'addr', 'add', f'{address}/24', 'dev', iface)
            ip('-n', ns, 'link', 'set', iface, 'up')
            ip('-n', ns, 'link', 'set', 'lo', 'up')
    except subprocess.CalledProcessError as e:
        for ns in names.values():
            subprocess.run(['ip', 'netns', 'del', ns], capture_output=True)
        prerequisite(False, f'cannot make network namespaces here: {e.stderr.decode().strip()}')

    def link(up: bool):
        ip('-n', names['capture'], 'link', 'set', links['capture'][0], 'up' if up else 'down')
    yield names, link
    for ns in names.values():
        subprocess.run(['ip', 'netns', 'del', ns], capture_output=True)


@pytest.mark.timeout(240)
def test_corrected_colour_crosses_hosts_and_survives_a_link_drop(studio_bag, hosts, procs):
    names, link = hosts
    env = dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE='SUBNET', VOLCAP_TRANSPORT='multihost')
    env.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)
    capture = ('ip', 'netns', 'exec', names['capture'])
    topic = f'/cam0/{topics.COLOR_CORRECTED}'
    receiver = subprocess.Popen(['ip', 'netns', 'exec', names['fusion'], sys.executable, '-c', RECEIVER, topic, '28'],
                                env=env, stdout=subprocess.PIPE, text=True)
    procs.append(start_node('volcap_color', 'color_corrector', {}, namespace='cam0', env=env, wrapper=capture))
    procs.append(start_node('volcap_driver', 'bag_player', {
        'bag': str(studio_bag), 'topics': [f'cam0/{topics.COLOR_IMAGE}'], 'loop': True, 'restamp': True,
        'exit_when_done': False, 'wait_for_subscribers': 20.0}, env=env, wrapper=capture))
    time.sleep(12)
    down = time.time_ns()
    link(False)
    time.sleep(2)
    up = time.time_ns()
    link(True)
    received = json.loads(receiver.communicate(timeout=120)[0].strip().splitlines()[-1])
    for proc in procs:
        assert proc.poll() is None           # nothing went down with the link
    assert stop(procs.pop()) == 0 and stop(procs.pop()) == 0
    before = [r for r, _ in received if r < down]
    during = [r for r, _ in received if down + 0.5e9 < r < up]
    after = [r for r, _ in received if r > up]
    assert len(before) >= 5                  # the corrected images reached the other host
    assert not during                        # the link was down
    assert after and (after[0] - up) / 1e9 < 10 and len(after) >= 5   # and the stream resumed
