"""One definition per setting: config fields carry their documentation and limits, and node
parameters, validation and the docs tables come from them."""
from dataclasses import dataclass, field

import pytest

from volcap_core import settings
from volcap_core.settings import setting


@dataclass
class Inner:
    gain: float = setting(1.0, 'gain', 0.0, 4.0)


@dataclass
class Outer:
    mode: str = setting('fast', 'mode', choices=('fast', 'exact'))
    inner: Inner = field(default_factory=Inner)
    size: tuple[int, int] = setting((2, 3), 'size (px)', 1, 10)
    centre: tuple[float, float, float] | None = setting(None, 'centre; [0.0]: automatic', none_as=[0.0])
    label: str = setting('', 'free text', read_only=True)


def test_nested_settings_are_flattened_in_parameter_form():
    assert [s.name for s in settings.settings(Outer)] == ['mode', 'gain', 'size', 'centre', 'label']
    defaults = {s.name: s.parameter_default for s in settings.settings(Outer)}
    assert defaults == {'mode': 'fast', 'gain': 1.0, 'size': [2, 3], 'centre': [0.0], 'label': ''}


def test_build_converts_parameters_back_and_validates():
    cfg = settings.build(Outer, {'gain': 2, 'size': [4, 5], 'centre': [1.0, 2.0, 3.0]})
    assert cfg.inner.gain == 2.0 and isinstance(cfg.inner.gain, float)
    assert cfg.size == (4, 5) and cfg.centre == (1.0, 2.0, 3.0)
    assert settings.build(Outer, {'centre': [0.0]}).centre is None
    with pytest.raises(ValueError, match='gain must be within 0.0 - 4.0'):
        settings.build(Outer, {'gain': 5.0})
    with pytest.raises(ValueError, match='size must be within'):
        settings.build(Outer, {'size': [0, 3]})
    with pytest.raises(ValueError, match='mode must be one of fast, exact'):
        settings.build(Outer, {'mode': 'slow'})
    with pytest.raises(ValueError, match='no setting colour'):
        settings.build(Outer, {'colour': 1})
    with pytest.raises(ValueError, match='must be a number'):
        settings.validate(Outer(inner=Inner(gain=float('nan'))))


def test_markdown_table_lists_every_setting():
    table = settings.markdown_table(Outer)
    assert '| `gain` | `1.0` | 0.0 - 4.0 | gain |' in table
    assert '| `mode` | `\'fast\'` | fast \\| exact | mode |' in table
    assert '(read-only)' in table


def test_stage_configs_validate_their_defaults_and_reject_out_of_range_values():
    from volcap_filter.pipeline import DepthFilterConfig
    from volcap_fusion.tsdf import FusionConfig
    DepthFilterConfig().validate()
    FusionConfig().validate()
    with pytest.raises(ValueError, match='voxel_size'):
        FusionConfig(voxel_size=0.5).validate()
    with pytest.raises(ValueError, match='min_axes'):
        settings.build(DepthFilterConfig, {'min_axes': 7})
    # each value in range, the combination not: the config's own validate() refuses it
    with pytest.raises(ValueError, match='min_range < max_range'):
        settings.build(DepthFilterConfig, {'min_range': 3.0})


@dataclass
class Command:
    """A command's config: a path that is not a setting, settings, a nested config whose own
    default differs from its class's, and a boolean on by default."""
    path: str
    voxel_size: float = setting(0.004, 'voxel edge (m)', 0.0005, 0.1, option='--voxel')
    inner: Inner = field(default_factory=lambda: Inner(gain=2.0))
    keep: bool = setting(True, 'keep it')
    quiet: bool = setting(False, 'say less')
    centre: tuple[float, float, float] | None = setting(None, 'centre', none_as=[0.0])


def test_command_line_options_come_from_the_settings_and_restate_no_default():
    import argparse
    p = argparse.ArgumentParser()
    settings.add_arguments(p, Command)
    help_text = p.format_help()
    assert 'voxel edge (m) (default: 0.004; 0.0005 - 0.1)' in help_text and '--voxel' in help_text
    assert '--no-keep' in help_text and '--quiet' in help_text and '--gain' in help_text
    given = p.parse_args([])
    assert settings.given_settings(Command, given) == {}           # nothing given: nothing restated
    cfg = settings.config_from_args(Command, given, path='x')
    assert cfg == Command('x') and cfg.inner.gain == 2.0           # the field's own nested default
    cfg = settings.config_from_args(Command, p.parse_args(['--voxel', '0.01', '--no-keep', '--quiet', '--gain',
                                                           '3', '--centre', '1', '2', '3']), path='x')
    assert (cfg.voxel_size, cfg.keep, cfg.quiet, cfg.inner.gain, cfg.centre) == (0.01, False, True, 3.0, (1.0, 2.0, 3.0))
    with pytest.raises(ValueError, match='voxel_size must be within'):
        settings.config_from_args(Command, p.parse_args(['--voxel-size', '1']), path='x')
    with pytest.raises(ValueError, match='gain must be within'):
        settings.config_from_args(Command, p.parse_args(['--gain', '9']), path='x')
    preset = argparse.ArgumentParser()
    settings.add_arguments(preset, Command, ['voxel_size'], defaults={'voxel_size': 0.01})
    assert '(default: 0.01;' in preset.format_help()
    assert settings.config_from_args(Command, preset.parse_args([]), defaults={'voxel_size': 0.01},
                                     path='x').voxel_size == 0.01
