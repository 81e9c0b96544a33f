"""One definition per setting: a config dataclass field carries its default, description and
allowed range or choices, and everything else is derived from it (node parameters, ``validate``,
the parameter tables in ``docs/``).

    @dataclass
    class FusionConfig:
        voxel_size: float = setting(0.004, 'TSDF voxel edge (m)', 0.0005, 0.1)

Nested config dataclasses are flattened (their field names must be unique within the outer
config). Tuples become ROS list parameters; ``None`` is stood for by ``none_as``. Command-line
options come from the same declarations (``add_arguments``, ``config_from_args``): the option's
name, type, help, range and choices are the setting's, and its default is the dataclass's, never
restated in argparse.
"""
from __future__ import annotations

import dataclasses
import typing
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from typing import Any

from .errors import BadInput


def setting(default=MISSING, description: str = '', low=None, high=None, *, choices: tuple | None = None,
            read_only: bool = False, none_as=None, default_factory=MISSING, option: str | tuple[str, ...] = ()):
    """A dataclass field with its documentation and limits.

    ``low``/``high`` bound numbers (and every element of a tuple); ``choices`` lists the allowed
    values; ``read_only`` settings take effect at start only; ``none_as`` is the list parameter
    value that stands for ``None``; ``option``: other spellings of its command-line option
    (``--voxel`` for ``voxel_size``, whose own option is ``--voxel-size``)."""
    metadata = {'description': description, 'low': low, 'high': high, 'choices': choices,
                'read_only': read_only, 'none_as': none_as,
                'option': (option,) if isinstance(option, str) else tuple(option)}
    if default_factory is not MISSING:
        return field(default_factory=default_factory, metadata=metadata)
    return field(default=default, metadata=metadata)


@dataclass(frozen=True)
class Setting:
    """One flattened setting of a config class."""
    name: str
    path: tuple[str, ...]        # attribute path from the outer config (nested configs)
    default: Any
    description: str
    low: Any
    high: Any
    choices: tuple | None
    read_only: bool
    none_as: Any
    options: tuple[str, ...] = ()   # other spellings of the command-line option
    kind: type = str                # the value's type on the command line (of each element of a tuple)
    arity: int = 1                  # values it takes on the command line (a tuple's length)

    @property
    def parameter_default(self):
        """The default as a ROS parameter value (lists for tuples, ``none_as`` for None)."""
        return to_parameter(self, self.default)

    @property
    def range_text(self) -> str:
        if self.choices:
            return ' \\| '.join(str(c) for c in self.choices)
        if self.low is not None and self.high is not None:
            return f'{self.low} - {self.high}'
        return ''


def _default(f: dataclasses.Field):
    if f.default is not MISSING:
        return f.default
    if f.default_factory is not MISSING:
        return f.default_factory()
    raise TypeError(f'setting {f.name} has no default')


def settings(cls) -> list[Setting]:
    """Every documented setting of a config class, nested configs flattened, in field order."""
    out: list[Setting] = []
    hints = typing.get_type_hints(cls)
    for f in fields(cls):
        if is_dataclass(hints.get(f.name)) and isinstance(hints.get(f.name), type):
            out += [dataclasses.replace(s, path=(f.name, *s.path)) for s in settings(hints[f.name])]
            continue
        m = f.metadata
        if 'description' not in m:
            continue
        default = _default(f)
        out.append(Setting(f.name, (f.name,), default, m['description'], m['low'], m['high'], m['choices'],
                           m['read_only'], m['none_as'], m.get('option', ()), _kind(default, hints.get(f.name)),
                           _arity(default, hints.get(f.name))))
    names = [s.name for s in out]
    if len(set(names)) != len(names):
        raise TypeError(f'{cls.__name__}: flattened setting names must be unique, got {names}')
    return out


def _kind(default, hint) -> type:
    """The command-line type of a setting: its default's (an element's, for tuples), else the
    first of bool, int, float, str its type hint names (a setting whose default is None)."""
    sample = default[0] if isinstance(default, tuple) and default else default
    if sample is not None and isinstance(sample, (bool, int, float, str)):
        return type(sample)
    args = typing.get_args(hint) or (hint,)
    for kind in (bool, int, float, str):
        if kind in args or any(kind in typing.get_args(a) for a in args):
            return kind
    return str


def _arity(default, hint) -> int:
    """How many values a setting takes: a tuple's length (its default's, or its type hint's)."""
    if isinstance(default, tuple):
        return len(default)
    for a in (hint, *typing.get_args(hint)):
        if typing.get_origin(a) is tuple:
            return len(typing.get_args(a))
    return 1


def to_parameter(s: Setting, value):
    if value is None:
        return s.none_as
    if isinstance(value, tuple):
        return list(value)
    return value


def from_parameter(s: Setting, value):
    if s.none_as is not None and list(value if isinstance(value, (list, tuple)) else [value]) == list(s.none_as):
        return None
    if isinstance(s.default, tuple) or (s.default is None and isinstance(value, (list, tuple))):
        return tuple(value)
    if isinstance(s.default, float) and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    return value


def build(cls, values: dict[str, Any], direct: dict[str, Any] | None = None):
    """A config of ``cls`` from flattened setting values (ROS parameter form); the others keep
    their defaults. ``direct``: constructor arguments that are not settings (the input path of a
    command), passed as they are. Raises BadInput for unknown names, values out of range and
    combinations the config's own ``validate()`` refuses."""
    specs = {s.name: s for s in settings(cls)}
    unknown = set(values) - set(specs)
    if unknown:
        raise BadInput(f'{cls.__name__} has no setting {", ".join(sorted(unknown))}')
    nested: dict[tuple, dict] = {(): dict(direct or {})}
    for name, value in values.items():
        s = specs[name]
        nested.setdefault(s.path[:-1], {})[s.path[-1]] = from_parameter(s, value)
    cfg = _construct(cls, (), nested)
    if hasattr(cfg, 'validate'):
        cfg.validate()       # the ranges, and the checks that span several fields
    else:
        validate(cfg)
    return cfg


def _construct(cls, prefix: tuple, nested: dict, base=None):
    """``cls`` from the values in ``nested`` (by attribute path); a nested config that is not
    given keeps the field's own default (its ``default_factory`` may differ from the nested
    class's defaults), and one that is given starts from it."""
    hints = typing.get_type_hints(cls)
    kwargs = dict(nested.get(prefix, {}))
    for f in fields(cls):
        sub = hints.get(f.name)
        if f.name in kwargs or not (isinstance(sub, type) and is_dataclass(sub)):
            continue
        path = (*prefix, f.name)
        own = _default(f) if f.default is not MISSING or f.default_factory is not MISSING else None
        if any(k[:len(path)] == path for k in nested):
            kwargs[f.name] = _construct(sub, path, nested, own)
        elif own is not None:
            kwargs[f.name] = own
    return dataclasses.replace(base, **kwargs) if base is not None else cls(**kwargs)


def validate(cfg) -> None:
    """Check every setting of ``cfg`` (nested configs too) against its range and choices; a
    config's own ``validate()`` calls this and adds the checks that span several fields."""
    for s in settings(type(cfg)):
        v = cfg
        for part in s.path:
            v = getattr(v, part)
        _check(s, v)


def _check(s: Setting, value) -> None:
    if value is None:
        if s.default is not None:
            raise BadInput(f'{s.name} must be set')
        return
    if s.choices is not None and value not in s.choices:
        raise BadInput(f'{s.name} must be one of {", ".join(map(str, s.choices))}, got {value!r}')
    items = value if isinstance(value, tuple) else (value,)
    for item in items:
        if isinstance(item, bool) or not isinstance(item, (int, float)):
            continue
        if item != item:
            raise BadInput(f'{s.name} must be a number, got {value!r}')
        if (s.low is not None and item < s.low) or (s.high is not None and item > s.high):
            raise BadInput(f'{s.name} must be within {s.low} - {s.high}, got {value!r}')


def markdown_table(cls) -> str:
    """The settings of ``cls`` as a Markdown table (parameter, default, range, description)."""
    rows = ['| parameter | default | range | description |', '|---|---|---|---|']
    for s in settings(cls):
        default = s.parameter_default
        text = repr(default) if isinstance(default, str) else str(default).lower() if isinstance(default, bool) \
            else str(default)
        rows.append(f'| `{s.name}` | `{text}` | {s.range_text} | {s.description}'
                    f'{" (read-only)" if s.read_only else ""} |')
    return '\n'.join(rows)


# Settings every node on camera streams shares (one definition, so their docs agree).
COLOR_TRANSPORTS = ('raw', 'compressed')


def color_transport_setting():
    return setting('raw', 'colour as sensor_msgs/Image on color/image_raw (raw) or JPEG CompressedImage on '
                   'color/image_raw/compressed', choices=COLOR_TRANSPORTS, read_only=True)


def tf_prefix_setting():
    return setting('', 'prepended to the camera_info frame ids when looking them up on /tf_static', read_only=True)


def add_arguments(parser, cls, names=None, exclude=(), defaults: dict | None = None) -> None:
    """The settings of ``cls`` (``names``: only these, in this order; less ``exclude``) as options
    of an argparse ``parser``: ``--voxel-size`` for ``voxel_size`` (and the setting's other
    spellings), its type, choices and help with the default and range. Options that are not
    given stay absent from the parsed arguments, so the dataclass's default applies
    (``config_from_args``). Booleans that default to False are flags; those that default to True
    take ``--no-...``; tuples take as many values as their default has; a setting that defaults
    to None takes a value or stays None."""
    import argparse
    specs = {s.name: s for s in settings(cls)}
    unknown = set(names or ()) - set(specs)
    if unknown:
        raise TypeError(f'{cls.__name__} has no setting {", ".join(sorted(unknown))}')
    for name in (names or list(specs)):
        if name in exclude:
            continue
        s = specs[name]
        flags = ['--' + s.name.replace('_', '-'), *s.options]
        default = (defaults or {}).get(s.name, s.default)
        shown = 'none' if default is None else ' '.join(map(str, default)) if isinstance(default, tuple) \
            else str(default).lower() if isinstance(default, bool) else repr(default) if default == '' else str(default)
        limits = f'; {s.low} - {s.high}' if s.low is not None and s.high is not None and not s.choices else ''
        help_text = f'{s.description} (default: {shown}{limits})'.replace('%', '%%')
        common = {'dest': s.name, 'default': argparse.SUPPRESS, 'help': help_text}
        if s.kind is bool:
            parser.add_argument(*flags, action='store_true' if not default else argparse.BooleanOptionalAction,
                                **common)
            continue
        if s.arity > 1:
            parser.add_argument(*flags, type=s.kind, nargs=s.arity, metavar=s.name.upper(), **common)
            continue
        parser.add_argument(*flags, type=s.kind, choices=s.choices, **common)


def given_settings(cls, args) -> dict[str, Any]:
    """The settings of ``cls`` given on the command line (``add_arguments``), by name."""
    return {s.name: getattr(args, s.name) for s in settings(cls) if hasattr(args, s.name)}


def config_from_args(cls, args, defaults: dict | None = None, **fixed):
    """A config of ``cls`` from the options the user gave (``add_arguments``) and ``fixed``
    values the command sets itself (settings, or constructor arguments that are not settings);
    every other setting keeps the dataclass's default. Validated as node parameters are: a value
    out of range or a bad combination is a ``BadInput``. ``defaults``: the command's preset, as
    given to ``add_arguments``."""
    specs = {s.name for s in settings(cls)}
    values = {**(defaults or {}), **given_settings(cls, args), **{k: v for k, v in fixed.items() if k in specs}}
    return build(cls, values, {k: v for k, v in fixed.items() if k not in specs})
