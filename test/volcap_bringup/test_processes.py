"""Stopping node processes (``volcap_bringup.processes``): no ROS, plain child processes that
behave as a node does on SIGINT, or as a hung one does."""
import signal
import subprocess
import sys
import time

from volcap_bringup.processes import stop, stop_all_timed

# A child that says it is ready once its SIGINT handling is in place, then waits to be stopped.
# ``clean``: SIGINT writes "<name> interrupted" and exits 3; ``hung``: SIGINT is ignored.
CHILD = r'''
import pathlib, signal, sys, time
name, mode, folder = sys.argv[1], sys.argv[2], pathlib.Path(sys.argv[3])
def on_sigint(*_):
    (folder / (name + '.log')).write_text(name + ' interrupted')
    sys.exit(3)
signal.signal(signal.SIGINT, on_sigint if mode == 'clean' else signal.SIG_IGN)
(folder / (name + '.ready')).touch()
time.sleep(120)
'''


def _start(tmp_path, name, mode):
    return subprocess.Popen([sys.executable, '-c', CHILD, name, mode, str(tmp_path)])


def _wait_ready(tmp_path, names, timeout=60.0):
    deadline = time.monotonic() + timeout
    while not all((tmp_path / f'{n}.ready').exists() for n in names):
        assert time.monotonic() < deadline, f'children not ready: {names}'
        time.sleep(0.05)


def test_stop_all_interrupts_every_process_and_kills_only_the_one_that_hangs(tmp_path):
    """Every process gets its SIGINT (each shuts down cleanly, exit code kept); one that ignores
    it is killed at the deadline; one that had already ended is left as it was."""
    done = subprocess.Popen([sys.executable, '-c', 'import sys; sys.exit(5)'])
    done.wait()
    first, hung, second = _start(tmp_path, 'first', 'clean'), _start(tmp_path, 'hung', 'hung'), \
        _start(tmp_path, 'second', 'clean')
    try:
        _wait_ready(tmp_path, ['first', 'hung', 'second'])
        stopped = stop_all_timed([first, hung, second, done], timeout=5.0)
    finally:
        for p in (first, hung, second):
            if p.poll() is None:
                p.kill()
                p.wait()
    codes, seconds = zip(*stopped)
    assert codes == (3, -signal.SIGKILL, 3, 5)
    # each timed from the signals; the hung one killed only after its 5 s; none for the one that had ended
    assert seconds[0] is not None and seconds[2] is not None and seconds[3] is None
    assert seconds[1] >= 5.0
    assert (tmp_path / 'first.log').read_text() == 'first interrupted'
    assert (tmp_path / 'second.log').read_text() == 'second interrupted'
    assert not (tmp_path / 'hung.log').exists()


def test_stop_is_stop_all_of_one(tmp_path):
    child = _start(tmp_path, 'only', 'clean')
    try:
        _wait_ready(tmp_path, ['only'])
        assert stop(child) == 3
    finally:
        if child.poll() is None:
            child.kill()
            child.wait()
    assert stop(child) == 3         # already stopped: nothing sent, its code kept
