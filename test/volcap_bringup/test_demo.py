"""`volcap demo` end to end on a short session, each node in its own process."""
import json

import pytest

from volcap_bringup.cli import main

pytestmark = pytest.mark.ros


@pytest.mark.timeout(900)
def test_demo_calibrates_runs_and_scores_without_an_error_line(tmp_path, capfd, shared_data):
    """`volcap demo` end to end on a short session: it renders the studio, calibrates the rig from
    its board views, runs the graph on the bag with that calibration (each node its own process)
    and scores the fused model against the truth; a healthy run prints no ERROR line, from any
    process."""
    out = tmp_path / 'demo'
    # the colour steps are test_color_eval's (harmonise, eval colour with the networks)
    assert main(['demo', '--out', str(out), '--frames', '2', '--no-colour', '--scored-frames', '2',
                 '--run-rate', '0.25']) == 0
    printed = capfd.readouterr()
    text = printed.out + printed.err
    errors = [line for line in text.splitlines() if 'ERROR' in line or 'Traceback' in line]
    assert not errors, errors[:5]
    assert '2 of 2 capture frame sets fused' in text
    run = json.loads((out / 'run' / 'metrics.json').read_text())
    assert run['frames_written'] == 2 and all(c == 0 for c in run['node_exit_codes'].values())
    fusion = json.loads((out / 'fusion.json').read_text())
    # calibrated from the board (16 poses), not the truth
    assert fusion['frames'] == 2 and fusion['accuracy_mm'] < 3.0 and fusion['completeness'] > 0.85, fusion
    # the feet and the colour seams are scored too (their targets are bench/end_to_end.py's)
    assert fusion['completeness_feet'] is not None and fusion['seams']['frames'] == 2
    assert fusion['seams']['seam_de'] is not None and 'through the calibration' in fusion['seams']['colours']
    assert 'seams:' in text
    assert 'colour steps left out' in text and not (out / 'colour.json').exists()
