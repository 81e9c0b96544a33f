"""The documentation a newcomer reads stays true: the parameter tables in docs/ are the config
dataclasses' settings, and every page the README links to exists."""
import re
from pathlib import Path

from volcap_bringup import docs

REPO = Path(__file__).resolve().parents[2]


def test_parameter_tables_match_the_code():
    assert docs.stale(REPO / 'docs') == [], 'run .venv/bin/python -m volcap_bringup.docs'


def test_every_node_parameter_is_documented():
    tables = ''.join(p.read_text() for p in (REPO / 'docs').glob('*.md'))
    listed = set(re.findall(r'<!-- parameters ([^>]*?) -->', tables))
    classes = {spec for block in listed for spec in block.split()}
    for spec in ('volcap_filter.session:DepthFilterNodeConfig', 'volcap_filter.pipeline:DepthFilterConfig',
                 'volcap_fusion.frame_sets:FusionNodeConfig', 'volcap_fusion.tsdf:FusionConfig',
                 'volcap_calib.session:CalibrationServiceConfig',
                 'volcap_color.color_corrector_node:ColorCorrectorConfig', 'volcap_color.config:ColorCorrectionConfig',
                 'volcap_driver.playback:BagPlayerConfig',
                 'volcap_driver.recorder_node:RecorderConfig', 'volcap_studio.synthetic_rig_node:SyntheticRigConfig'):
        assert spec in classes, f'{spec} has no parameter table in docs/'


def test_a_stale_table_is_found_and_rewritten(tmp_path):
    page = tmp_path / 'page.md'
    page.write_text('x\n<!-- parameters volcap_fusion.frame_sets:FusionNodeConfig -->\nold\n<!-- end parameters -->\n')
    assert docs.stale(tmp_path) == [page]
    assert docs.main([str(tmp_path)]) == 0
    assert docs.stale(tmp_path) == [] and '| `min_cameras` | `1` | 1 - 64 |' in page.read_text()


def test_readme_links_resolve():
    for link in re.findall(r'\]\(([^)#]+)\)', (REPO / 'README.md').read_text()):
        assert (REPO / link).exists(), link
