"""YAML overrides for the frozen dataclass configs. A YAML file holds overrides only; an unknown key is an error.

>>> from configs import load_config
>>> cfg = load_config(EnKTSConfig, "planner.yaml", n_particles=100)
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, TypeVar

import yaml

CONFIG_DIR = Path(__file__).resolve().parent
T = TypeVar("T")


def _plain(value: Any) -> Any:
    """YAML lists become tuples (the configs are frozen and hashable); '.inf' already parses to float inf."""
    if isinstance(value, list):
        return tuple(_plain(v) for v in value)
    return value


def load_config(cls: type[T], source: str | Path | None = None, **overrides: Any) -> T:
    """Build ``cls`` from its defaults, then the YAML ``source`` (a path, or a file name under ``configs/``),
    then ``overrides``. Raises ``ValueError`` naming any key that ``cls`` does not have."""
    values: dict[str, Any] = {}
    if source is not None:
        path = Path(source)
        if not path.is_file():
            path = CONFIG_DIR / path
        data = yaml.safe_load(path.read_text()) or {}
        if not isinstance(data, dict):
            raise ValueError(f"{path}: expected a mapping of overrides, got {type(data).__name__}")
        values.update({k: _plain(v) for k, v in data.items()})
    values.update({k: _plain(v) for k, v in overrides.items()})
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - fields)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} key(s) {unknown}; valid keys: {sorted(fields)}")
    return cls(**values)


__all__ = ["CONFIG_DIR", "load_config"]
