"""Typed, frozen configs: presets, JSON, ``field=value`` overrides and command-line options, from
the fields themselves, so that no default or choice is written twice.

A config is a frozen dataclass whose fields carry their help text in ``metadata`` (:func:`option`).
Values given as text (``--set section.field=value``, generated command-line options) are parsed by
the field's annotation: ``int``, ``float``, ``str``, ``bool``, ``Optional[...]`` (``none``) and
``tuple[int, ...]`` / ``tuple[str, ...]`` (comma-separated).
"""

from __future__ import annotations

import dataclasses
from typing import Any


def option(default: Any, help: str, choices=None):  # pylint: disable=redefined-builtin
    """A config field with its help text (and allowed values) where the command line can read them."""
    return dataclasses.field(default=default, metadata={'help': help, 'choices': choices})


def _annotation(cls, name: str) -> str:
    hints = {}
    for klass in reversed(cls.__mro__):
        hints.update(getattr(klass, '__annotations__', {}))
    t = hints[name]
    return t if isinstance(t, str) else getattr(t, '__name__', str(t))


def parse_value(cls, name: str, text: str) -> Any:
    """``text`` as a value of field ``name`` of config class ``cls``; a ValueError names the field."""
    ann = _annotation(cls, name).replace('typing.', '').replace(' ', '')
    optional = ann.startswith('Optional[') or ann.endswith('|None')
    if optional:
        ann = ann[len('Optional['):-1] if ann.startswith('Optional[') else ann[:-len('|None')]
        if text.strip().lower() == 'none':
            return None
    try:
        if ann.startswith('tuple['):
            elem = int if 'int' in ann else (float if 'float' in ann else str)
            return tuple(elem(x) for x in text.split(',') if x.strip())
        if ann == 'bool':
            low = text.strip().lower()
            if low not in ('1', '0', 'true', 'false', 'yes', 'no'):
                raise ValueError(f'expected true or false, got {text!r}')
            return low in ('1', 'true', 'yes')
        if ann == 'int':
            return int(text)
        if ann == 'float':
            return float(text)
        return text
    except ValueError as e:
        raise ValueError(f'{cls.__name__}.{name} ({ann}): cannot read {text!r}: {e}') from None


def field_names(cls) -> list[str]:
    return [f.name for f in dataclasses.fields(cls)]


def from_dict(cls, d: dict):
    """``cls`` from a JSON dict (lists become tuples); unknown fields are an error that names them."""
    if not isinstance(d, dict):
        raise ValueError(f'{cls.__name__}: expected a JSON object, got {type(d).__name__}')
    unknown = set(d) - set(field_names(cls))
    if unknown:
        raise ValueError(f'unknown {cls.__name__} field(s) {sorted(unknown)}')
    return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})


def with_overrides(cfg, pairs) -> Any:
    """``['batch_size=64', 'q_hidden=64,64']`` -> a new config, each value parsed by its field's type."""
    names = field_names(type(cfg))
    changes = {}
    for pair in pairs:
        if '=' not in pair:
            raise ValueError(f'override {pair!r} is not of the form key=value')
        k, v = pair.split('=', 1)
        if k not in names:
            raise ValueError(f'unknown {type(cfg).__name__} field {k!r}; expected one of {", ".join(names)}')
        changes[k] = parse_value(type(cfg), k, v)
    return dataclasses.replace(cfg, **changes)


def _matches(ann: str, value) -> bool:
    """Whether ``value`` is of the annotated type (``int`` is accepted where a ``float`` is)."""
    ann = ann.replace('typing.', '').replace(' ', '')
    if ann.startswith('Optional['):
        return value is None or _matches(ann[len('Optional['):-1], value)
    if ann.endswith('|None'):
        return value is None or _matches(ann[:-len('|None')], value)
    if ann.startswith('tuple['):
        elem = ann[len('tuple['):-1].split(',')[0]
        return isinstance(value, tuple) and all(_matches(elem, v) for v in value)
    if ann == 'bool':
        return isinstance(value, bool)
    if ann == 'int':
        return isinstance(value, int) and not isinstance(value, bool)
    if ann == 'float':
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if ann == 'str':
        return isinstance(value, str)
    return True  # other annotations are checked by their config


def check_types(cfg) -> None:
    """Every field holds a value of its annotated type; the error names the field (a config read
    from an edited JSON file, or built in code with a wrong value)."""
    for f in dataclasses.fields(cfg):
        ann = _annotation(type(cfg), f.name)
        v = getattr(cfg, f.name)
        if not _matches(ann, v):
            raise ValueError(f'{type(cfg).__name__}.{f.name} must be {ann.replace("typing.", "")}; got {v!r}')


def check_widths(cfg, *names) -> None:
    """Layer-width tuples: at least one layer, every width an integer >= 1."""
    for name in names:
        v = getattr(cfg, name)
        if not v or any(isinstance(w, bool) or not isinstance(w, int) or w < 1 for w in v):
            raise ValueError(f'{type(cfg).__name__}.{name} must be one or more layer widths >= 1; got {v!r}')


def check_choice(cls_name: str, name: str, value, allowed) -> None:
    if value not in allowed:
        raise ValueError(f'{cls_name}.{name}: unknown value {value!r}; expected one of {", ".join(map(str, allowed))}')


def check_positive_int(cfg, *names) -> None:
    for name in names:
        v = getattr(cfg, name)
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f'{type(cfg).__name__}.{name} must be an integer >= 1; got {v!r}')
