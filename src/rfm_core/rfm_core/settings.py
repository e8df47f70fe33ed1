"""Typed, described settings: the machinery behind :mod:`rfm_core.config`.

Every threshold of rfm is a field of a frozen dataclass declared with :func:`setting` (a node
parameter: default, description, range, the paper's value), :func:`constant` (a value of the
method that is no parameter: documented and typed in the same place, set only in code) or
:func:`section` (a nested stage). From
the dataclasses alone, :func:`settings_of` lists every setting under its dotted name, which
is also its ROS parameter name (``keyframes.min_overlap``); :func:`with_values` builds a
configuration from such names, checking types, ranges and choices; :func:`from_dict` reads
the nested dictionaries stored in map files; :func:`markdown_table` writes the README's
parameter tables. No ROS imports here: :func:`rfm_core.io.parameters.declare_config` turns
the same listing into ROS parameters.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, is_dataclass, replace

__all__ = ['setting', 'constant', 'section', 'same_setting', 'Setting', 'settings_of', 'with_values', 'from_dict', 'markdown_table']


def setting(default, description: str, *, lo=None, hi=None, paper=None, choices=None,
            read_only: bool = False, ros: bool = True):
    """A dataclass field that is a setting: ``default``, what it does, its range [lo, hi],
    the paper's value, the allowed ``choices`` (strings), whether it can only be set at
    start-up (``read_only``), and whether it is a node parameter at all (``ros``)."""
    meta = dict(description=description, lo=lo, hi=hi, paper=paper,
                choices=tuple(choices) if choices else None, read_only=read_only, ros=ros)
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda: type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


def constant(default, description: str, *, lo=None, hi=None, paper=None, choices=None):
    """A dataclass field that is a value of the method, not a node parameter: what it is, its
    unit and range, the paper's value. Tests, benchmarks and training set it in code; a user
    never needs to (a stage's internals, noise models, solver budgets)."""
    return setting(default, description, lo=lo, hi=hi, paper=paper, choices=choices, ros=False)


def section(cls, description: str = '', *, inline: bool = False, exclude=()):
    """A nested stage configuration: its settings are named ``<field>.<setting>`` (or without
    the prefix when ``inline``); settings named in ``exclude`` are not listed (the enclosing
    configuration sets them)."""
    return field(default_factory=cls, metadata=dict(description=description, section=True, inline=inline,
                                                    exclude=tuple(exclude)))


def same_setting(cls, name: str):
    """A field declared like ``cls``'s setting ``name`` (a setting two configurations share)."""
    f = cls.__dataclass_fields__[name]
    return field(default=f.default, default_factory=f.default_factory, metadata=f.metadata)


@dataclass(frozen=True)
class Setting:
    name: str                     #: dotted, relative to the configuration listed
    default: object
    description: str
    lo: float | None = None
    hi: float | None = None
    paper: object = None
    choices: tuple | None = None
    read_only: bool = False

    @property
    def kind(self) -> str:
        """bool, int, float, str or float[]."""
        value = self.default
        if isinstance(value, bool):
            return 'bool'
        if isinstance(value, int):
            return 'int'
        if isinstance(value, float):
            return 'float'
        if isinstance(value, (list, tuple)):
            return 'float[]'
        return 'str'

    def check(self, value):
        """``value`` as this setting's type; ValueError saying what is wrong."""
        kind = self.kind
        if kind == 'bool':
            if not isinstance(value, bool):
                raise ValueError(f'{self.name}: expected true or false, got {value!r}')
            return value
        if kind in ('int', 'float'):
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f'{self.name}: expected a finite number, got {value!r}')
            if kind == 'int':
                if value != int(value):
                    raise ValueError(f'{self.name}: expected an integer, got {value!r}')
                value = int(value)
            else:
                value = float(value)
            if (self.lo is not None and value < self.lo) or (self.hi is not None and value > self.hi):
                raise ValueError(f'{self.name}: {value} is outside [{self.lo}, {self.hi}]')
            return value
        if kind == 'float[]':
            try:
                values = [float(v) for v in value]
            except (TypeError, ValueError):
                raise ValueError(f'{self.name}: expected a list of numbers, got {value!r}') from None
            if len(values) != len(self.default) or not all(math.isfinite(v) for v in values):
                raise ValueError(f'{self.name}: expected {len(self.default)} finite numbers, got {value!r}')
            return values
        if not isinstance(value, str):
            raise ValueError(f'{self.name}: expected a string, got {value!r}')
        if self.choices and value not in self.choices:
            raise ValueError(f'{self.name}: {value!r} is not one of {", ".join(self.choices)}')
        return value


def _sections(config):
    for f in fields(config):
        if f.metadata.get('section'):
            yield f, getattr(config, f.name)


def settings_of(config, prefix: str = '', exclude=()) -> list[Setting]:
    """Every setting of a configuration (instance or class) under its dotted name, with the
    instance's values as defaults, in declaration order."""
    if isinstance(config, type):
        config = config()
    out = []
    for f in fields(config):
        if f.name in exclude:
            continue
        meta = f.metadata
        value = getattr(config, f.name)
        if meta.get('section'):
            sub = prefix if meta['inline'] else f'{prefix}{f.name}.'
            out += settings_of(value, sub, meta['exclude'])
        elif 'description' not in meta:
            raise TypeError(f'{type(config).__name__}.{f.name} is not declared with setting() or section()')
        elif meta['ros']:
            out.append(Setting(prefix + f.name, value, meta['description'], meta['lo'], meta['hi'],
                               meta['paper'], meta['choices'], meta['read_only']))
    return out


def with_values(config, values: dict):
    """``config`` with the settings in ``values`` (dotted names as :func:`settings_of` lists
    them) replaced, each checked against its declaration. ValueError for an unknown name or a
    bad value."""
    known = {s.name: s for s in settings_of(config)}
    unknown = sorted(set(values) - set(known))
    if unknown:
        raise ValueError(f'unknown setting(s) of {type(config).__name__}: {", ".join(unknown)}')
    return _replace(config, {name: known[name].check(v) for name, v in values.items()}, '')


def _replace(config, values: dict, prefix: str):
    changes = {}
    for f in fields(config):
        meta = f.metadata
        if meta.get('section'):
            sub = prefix if meta['inline'] else f'{prefix}{f.name}.'
            if any(name.startswith(sub) for name in values):
                changes[f.name] = _replace(getattr(config, f.name), values, sub)
        elif prefix + f.name in values:
            changes[f.name] = values[prefix + f.name]
    return replace(config, **changes) if changes else config


def from_dict(cls, values: dict):
    """A configuration from nested dictionaries (``dataclasses.asdict`` of one, as map files
    store it): settings it lacks keep their defaults, unknown ones are ignored (files of other
    rfm versions). Each value is checked as a parameter is (:meth:`Setting.check`: its type,
    range and choices): ValueError naming the setting for one that is not."""
    if not isinstance(values, dict):
        raise ValueError(f'{cls.__name__}: expected a mapping, got {type(values).__name__}')
    kwargs = {}
    default = cls()
    for f in fields(cls):
        if f.name not in values:
            continue
        current, value, meta = getattr(default, f.name), values[f.name], f.metadata
        if is_dataclass(current):
            kwargs[f.name] = from_dict(type(current), value)
        elif 'description' in meta:
            kwargs[f.name] = Setting(f'{cls.__name__}.{f.name}', current, '', meta['lo'], meta['hi'],
                                     choices=meta['choices']).check(value)
    return cls(**kwargs)


def _format(value) -> str:
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        return f'`{value}`' if value else "''"
    if isinstance(value, (list, tuple)):
        return '[' + ', '.join(_format(v) for v in value) + ']'
    return f'{value:g}' if isinstance(value, float) else str(value)


def markdown_table(settings: list[Setting]) -> str:
    """A README table: parameter, default, meaning (with the range, the paper's value, the
    choices, and whether it is read at start-up only)."""
    rows = ['| parameter | default | meaning |', '|---|---|---|']
    for s in settings:
        notes = []
        if s.lo is not None and s.hi is not None:
            notes.append(f'{_format(s.lo)} to {_format(s.hi)}')
        if s.choices:
            notes.append('one of ' + ', '.join(f'`{c}`' for c in s.choices))
        if s.paper is not None:
            notes.append(f'paper: {s.paper if isinstance(s.paper, str) else _format(s.paper)}')
        if s.read_only:
            notes.append('start-up only')
        text = s.description.replace('|', '\\|') + (f' ({"; ".join(notes)})' if notes else '')
        rows.append(f'| `{s.name}` | {_format(s.default)} | {text} |')
    return '\n'.join(rows) + '\n'
