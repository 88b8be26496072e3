"""Configuration helpers: every stage has a typed ``@dataclass``; these map dicts/YAML onto it.

The resolved configuration is written next to every output (``config.yaml``) so a run can be
reproduced.
"""

from __future__ import annotations

import dataclasses
import typing
from pathlib import Path
from typing import Any, Type, TypeVar

import yaml

T = TypeVar("T")


def from_dict(cls: Type[T], data: dict | None) -> T:
    """Build dataclass ``cls`` from a (possibly nested) dict, rejecting unknown keys."""
    data = dict(data or {})
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} option(s) {unknown}; known: {sorted(names)}")
    kwargs: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        v = data[f.name]
        t = hints.get(f.name)
        if dataclasses.is_dataclass(t) and isinstance(v, dict):
            v = from_dict(t, v)
        kwargs[f.name] = v
    return cls(**kwargs)


def to_dict(obj: Any) -> dict:
    """Plain-dict form of a (nested) config dataclass, suitable for YAML/JSON."""
    return dataclasses.asdict(obj)


def write_yaml(obj: Any, path: str | Path) -> None:
    """Write a config dataclass (or dict) as YAML."""
    data = to_dict(obj) if dataclasses.is_dataclass(obj) else obj
    Path(path).write_text(yaml.safe_dump(data, sort_keys=False))


def load_yaml(path: str | Path) -> dict:
    """Read a YAML mapping ({} for an empty file)."""
    data = yaml.safe_load(Path(path).read_text()) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a YAML mapping at the top level")
    return data
