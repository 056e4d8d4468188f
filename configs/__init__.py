"""The frozen dataclass configs: YAML overrides and one field check shared by every config.

A YAML file holds overrides only; an unknown key is an error.

>>> from bimp.configs import load_config
>>> cfg = load_config(EnKTSConfig, "planner.yaml", n_particles=100)

Every config calls :func:`check_fields` first thing in its ``__post_init__``, so a value of the wrong type is
rejected however the config is built (YAML, keyword overrides, direct construction), and then checks its own
ranges. Both raise :class:`ConfigError` (a ``ValueError``) naming the key and the value:
``n_particles must be an int, got 50.7``.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import numbers
import os
import stat
import types
import typing
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

import yaml

CONFIG_DIR = Path(__file__).resolve().parent
# Tuned configs written by `bimp tune` (configs/tuned/NAME.yaml): where one ships, it is policy NAME's default.
TUNED_DIR = CONFIG_DIR / "tuned"
T = TypeVar("T")
# Keys that make bimp run code from a file it loads (trust_model: an RL model unpickled by SB3's own load). They come
# from the command line or the Python call only: a config file that sets one is refused (docs/security.md).
TRUST_SWITCHES = frozenset({"trust_model"})


class ConfigError(ValueError):
    """A rejected config value. ``key``: the field (dotted inside a nested config: ``barrier.widths``),
    ``value``: what it was given, ``requirement``: what it must be. Message:
    ``"{key} must be {requirement}, got {value!r}"``, then ``" ({detail})"`` if a detail is given."""

    def __init__(self, key: str, requirement: str, value: Any, detail: str = "") -> None:
        self.key, self.requirement, self.value, self.detail = key, requirement, value, detail
        super().__init__(f"{key} must be {requirement}, got {value!r}" + (f" ({detail})" if detail else ""))

    def under(self, parent: str) -> ConfigError:
        """The same error for the field seen from the config holding it in ``parent``."""
        return ConfigError(f"{parent}.{self.key}", self.requirement, self.value, self.detail)


def _plain(value: Any) -> Any:
    """YAML lists become tuples (the configs are frozen and hashable); '.inf' already parses to float inf."""
    if isinstance(value, list):
        return tuple(_plain(v) for v in value)
    return value


def read_yaml(path: str | Path) -> Any:
    """The YAML document in the file ``path``, read with ``safe_load`` (no tag builds an object). A file that cannot
    be read, is not UTF-8 text or not YAML raises ``ValueError`` in one line naming the file and, for bad YAML, the
    line and column (yaml's own message names a ``"<unicode string>"``); so does one that sets a key of
    :data:`TRUST_SWITCHES`, at any depth."""
    doc = _parse_yaml(path)
    switch = trust_switch(doc)
    if switch is not None:
        raise ValueError(f"{path} sets {switch}, a trust switch, which no file may set: give it on the command line "
                         f"(--set POLICY.{switch.rpartition('.')[2]}=true) or in the Python call (docs/security.md)")
    return doc


def trust_switch(doc: Any) -> str | None:
    """The dotted key of a :data:`TRUST_SWITCHES` key set in ``doc`` (a parsed file: YAML or JSON), None when none
    is."""
    stack, seen = [(doc, "")], set()
    while stack:  # no recursion: a crafted file may nest as deep as the parser lets it
        node, where = stack.pop()
        if id(node) in seen:  # YAML aliases share nodes (``a: &a [*a]`` is a cycle): each is walked once
            continue
        seen.add(id(node))
        children = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
        for key, value in children:
            path = f"{where}.{key}" if where else str(key)
            if isinstance(key, str) and key in TRUST_SWITCHES:
                return path
            stack.append((value, path))
    return None


MAX_YAML_BYTES = 16 << 20  # a config is a few kB; a bigger file is not one (nor a device behind a symlink)


def _parse_yaml(path: str | Path) -> Any:
    try:
        info = os.stat(path)
        if not stat.S_ISREG(info.st_mode):
            raise ValueError(f"{path}: cannot be read as a config (not a regular file)")
        if info.st_size > MAX_YAML_BYTES:
            raise ValueError(f"{path}: {info.st_size} bytes, over the {MAX_YAML_BYTES} a config may hold")
        return yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except RecursionError:
        raise ValueError(f"{path}: not a YAML config (nested too deep to read)") from None
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a UTF-8 text file, so not a YAML config") from None
    except OSError as err:
        raise ValueError(f"{path}: cannot be read ({err.strerror or err})") from None
    except yaml.MarkedYAMLError as err:
        mark = err.problem_mark or err.context_mark
        where = f", line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        raise ValueError(f"{path}{where}: not valid YAML: {err.problem or err.context}") from None
    except yaml.reader.ReaderError as err:  # a control character: no mark, a position
        raise ValueError(f"{path}, character {err.position + 1}: not valid YAML: {err.reason}") from None
    except yaml.YAMLError as err:
        raise ValueError(f"{path}: not valid YAML: {' '.join(str(err).split())}") from None


def read_overrides(source: str | Path) -> dict[str, Any]:
    """The mapping of a YAML file of overrides, ``source`` a path or a file name under ``configs/`` (an empty file:
    ``{}``). ``ValueError`` naming the file when it is not YAML (:func:`read_yaml`), not a mapping, or a tuned config
    in the old envelope (``policy``, ``tuning`` and ``config`` around the config), naming the command that splits it.
    """
    path = Path(source)
    if not path.is_file():
        path = CONFIG_DIR / path
    data = read_yaml(path) or {}
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping of overrides, got {type(data).__name__}")
    if is_old_tuned(data):
        raise ValueError(f"{path} is a tuned config in the old shape (policy, tuning and config around the config): "
                         f"`bimp migrate {path}` writes it as today's (the config alone, its tuning beside it in "
                         f"{tuning_path(path).name})")
    return data


def is_old_tuned(doc: Any) -> bool:
    """Whether ``doc`` (a parsed YAML) is a tuned config in the envelope ``bimp tune`` wrote before the tuning
    moved beside the config: ``{policy, tuning, config}``."""
    return isinstance(doc, dict) and {"policy", "config"} <= set(doc) and isinstance(doc["config"], dict) \
        and set(doc) <= {"policy", "tuning", "config"}


# --- tuned configs ----------------------------------------------------------------------------------------------
# A tuned config is a YAML of overrides like any other (the full config ``bimp tune`` chose); what the tuning was
# (the policy, the study, its budget and the chosen values) lies beside it in NAME.tuning.yaml, read by people and
# by the check that a config tuned for one policy is not loaded for another.
TUNING_SUFFIX = ".tuning.yaml"


def tuning_path(path: str | Path) -> Path:
    """Where the tuning record of the config ``path`` lies: ``best.yaml`` -> ``best.tuning.yaml``."""
    path = Path(path)
    return path.with_name(path.name.removesuffix(".yaml").removesuffix(".yml") + TUNING_SUFFIX)


def check_tuned_for(policy: str, path: str | Path) -> None:
    """``ValueError`` if the config ``path`` was tuned for a policy other than ``policy`` (its tuning record beside
    it says which); nothing for a config without one."""
    record = tuning_path(path)
    if record.is_file():
        doc = read_yaml(record)
        tuned = doc.get("policy") if isinstance(doc, dict) else None
        if tuned != policy:
            raise ValueError(f"{path} holds a config tuned for {tuned!r}, not {policy!r} ({record.name})")


def tuned_files(path: str | Path, config: Mapping[str, Any], policy: str,
                tuning: Mapping[str, Any] | None) -> dict[Path, str]:
    """The two files of a tuned config, ``{file: text}``: ``path`` the ``config`` alone (a YAML of overrides), and
    ``NAME.tuning.yaml`` beside it the ``policy`` and the ``tuning`` (the study, its budget and the chosen values).
    The caller writes them (``bimp.agents.files.write_atomic``)."""
    path = Path(path)
    record = {"policy": policy, **({"tuning": dict(tuning)} if tuning is not None else {})}
    return {
        tuning_path(path): f"# What `bimp tune` chose {path.name} by: the study, its budget, the values.\n"
        + yaml.safe_dump(record, sort_keys=False, default_flow_style=None, width=110),
        path: f"# Tuned by `bimp tune` for {policy}; its tuning: {tuning_path(path).name}. Load with "
        f"make_policy({policy!r}, env, config=<this file>).\n"
        + yaml.safe_dump(dict(config), sort_keys=False, default_flow_style=None, width=110),
    }


def merged(base: dict, top: Mapping) -> dict:
    """``top`` over ``base``, nested mappings (and configs, taken as their mappings) merged key by key."""
    out = dict(base)
    for key, value in top.items():
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            value = dataclasses.asdict(value)
        nested = isinstance(value, Mapping) and isinstance(out.get(key), dict)
        out[key] = merged(out[key], value) if nested else value
    return out


def load_config(cls: type[T], source: str | Path | Sequence[str | Path] | None = None, **overrides: Any) -> T:
    """Build ``cls`` from its defaults, then the YAML ``source`` (a path, or a file name under ``configs/``; or a
    list of them, later ones overriding earlier ones), then ``overrides``. Raises ``ValueError`` naming a file that is
    not a YAML mapping (:func:`read_yaml`) and any key that ``cls`` does not have, and whatever ``cls`` raises for a
    bad value (:class:`ConfigError` for the configs that call :func:`check_fields`).

    ``load_config(cls, None, **dataclasses.asdict(config))`` rebuilds ``config``; so does dumping that dict to
    YAML and loading the file (nested configs come back from their mappings)."""
    values: dict[str, Any] = {}
    sources = [] if source is None else [source] if isinstance(source, (str, Path)) else list(source)
    for source in sources:  # later files override earlier ones
        values.update({k: _plain(v) for k, v in read_overrides(source).items()})
    values.update({k: _plain(v) for k, v in overrides.items()})
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - fields, key=str)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} key(s) {unknown}; valid keys: {sorted(fields)}")
    return cls(**values)


def load_layered(cls: type[T], *layers: str | Path | Mapping[str, Any] | None, base: Mapping[str, Any] | None = None,
                 moved: Mapping[str, str] | None = None) -> T:
    """``cls`` built in layers, each over the one before: ``cls``'s defaults, ``base`` (a mapping), then ``layers``
    in order, each a YAML file of overrides (a path, or a name under ``configs/``), a mapping, or None (skipped).
    Nested mappings merge key by key, so ``problem: {horizon: 30}`` keeps the rest of the problem, and a dotted key
    is the nested one (``{"problem.horizon": 30}``: what ``--set POLICY.problem.horizon=30`` gives).

    ``moved``: ``{old dotted key: new dotted key}`` of renamed settings; a layer that sets an old key (or one under
    it), nested or dotted, raises ``ValueError`` naming its new place: one name per setting, no aliases. Other
    unknown keys and bad values raise as :func:`load_config` does."""
    tree: dict[str, Any] = merged({}, base or {})
    moved = dict(moved or {})
    for layer in layers:
        if layer is None:
            continue
        if not isinstance(layer, Mapping):
            layer = read_overrides(layer)
        for key, value in _leaves(layer):
            new = renamed_key(key, moved)
            if new is not None:
                hint = (f" (a planner's problem settings sit under problem: --set POLICY.{new}=...)"
                        if new.startswith("problem.") and key.partition(".")[0] in moved else "")
                raise ValueError(f"{key} is now {new}{hint}")
            for name in reversed(key.split(".")):
                value = {name: value}
            tree = merged(tree, value)
    return load_config(cls, None, **tree)


def renamed_key(key: str, moved: Mapping[str, str]) -> str | None:
    """The new dotted name of ``key`` where ``moved`` (``{old dotted key: new}``) renames it or a key above it
    (``problem.barrier.brake_decel.x`` under ``problem.barrier.brake_decel``); None where it keeps its name."""
    for old, new in moved.items():
        if key == old or key.startswith(old + "."):
            return new + key[len(old):]
    return None


def _leaves(layer: Mapping) -> list[tuple[str, Any]]:
    """``layer``'s settings as ``(dotted key, value)``, nested mappings walked (an empty one kept as a value)."""
    out = []
    for key, value in layer.items():
        if isinstance(value, Mapping) and value:
            out += [(f"{key}.{k}", v) for k, v in _leaves(value)]
        else:
            out.append((str(key), value))
    return out


# --- field check ----------------------------------------------------------------------------------------------
_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    # ``from __future__ import annotations`` leaves the annotations as strings: resolve them once per class.
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


def _number(key: str, value: Any, allow_inf: bool) -> float:
    finite = "a finite number" if not allow_inf else "a number (inf allowed)"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ConfigError(key, finite, value)
    try:
        value = float(value)
    except OverflowError:  # an integer past float's range
        raise ConfigError(key, finite, value) from None
    if math.isnan(value) or (math.isinf(value) and not allow_inf):
        raise ConfigError(key, finite, value)
    return value


def _check_value(key: str, hint: Any, value: Any, allow_inf: bool) -> Any:
    """``value`` checked against the annotation ``hint``, normalized (int/float of the plain Python type, tuples,
    nested configs built from mappings); raises :class:`ConfigError`."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if hint is Any:
        return value
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        options = [a for a in args if a is not type(None)]
        if len(options) != 1:
            raise TypeError(f"check_fields: unsupported annotation {hint} of {key}")
        try:
            return _check_value(key, options[0], value, allow_inf)
        except ConfigError as err:
            if err.key != key:  # an element or nested field: its own message is the precise one
                raise
            none = " or None" if type(None) in args else ""
            raise ConfigError(key, err.requirement + none, value, err.detail) from None
    if origin is typing.Literal:
        if value not in args or type(value) not in {type(a) for a in args}:
            raise ConfigError(key, "one of " + ", ".join(repr(a) for a in args), value)
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(key, "a bool (true or false)", value)
        return value
    if hint is int:
        # No integral floats (50.0): an int field given a float is more likely a slip than an intent.
        if isinstance(value, bool) or not isinstance(value, numbers.Integral):
            raise ConfigError(key, "an int", value)
        return int(value)
    if hint is float:
        return _number(key, value, allow_inf)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(key, "a string", value)
        return value
    if origin is tuple:
        variable = len(args) == 2 and args[1] is Ellipsis
        element = args[0] if variable else None
        names = {float: "numbers", int: "ints", str: "strings", bool: "bools"}
        if variable:
            what = f"a list of {names.get(element, element)}"
        elif len(set(args)) == 1:
            what = f"a list of {len(args)} {names.get(args[0], args[0])}"
        else:
            what = f"a list of {len(args)} entries ({', '.join(getattr(a, '__name__', str(a)) for a in args)})"
        if isinstance(value, (str, bytes, Mapping)) or not isinstance(value, Iterable):
            raise ConfigError(key, what, value)
        items = tuple(value)
        if not variable and len(items) != len(args):
            raise ConfigError(key, what, value, f"length {len(items)}")
        kinds = [element] * len(items) if variable else list(args)
        return tuple(_check_value(f"{key}[{i}]", k, v, allow_inf) for i, (k, v) in enumerate(zip(kinds, items)))
    if isinstance(hint, type) and dataclasses.is_dataclass(hint):
        if isinstance(value, hint):
            return value  # checked when it was built
        if not isinstance(value, Mapping):
            raise ConfigError(key, f"a {hint.__name__} or a mapping of its keys", value)
        try:
            return load_config(hint, None, **{str(k): v for k, v in value.items()})
        except ConfigError as err:
            raise err.under(key) from None
        except (ValueError, TypeError) as err:
            raise ValueError(f"{key}: {err}") from None
    if isinstance(hint, type):
        if not isinstance(value, hint):
            raise ConfigError(key, f"a {hint.__name__}", value)
        return value
    raise TypeError(f"check_fields: unsupported annotation {hint} of {key}")


def check_fields(config: Any, allow_inf: Iterable[str] = ()) -> None:
    """Check every field of the dataclass instance ``config`` against its type annotation, in place.

    Call it first thing in ``__post_init__`` (frozen or not), then check ranges, raising :class:`ConfigError`::

        def __post_init__(self) -> None:
            check_fields(self)
            if self.n_steps < 1:
                raise ConfigError("n_steps", "an int >= 1", self.n_steps)

    Rules: ``int``: an int, not a bool and not a float (not even 50.0); ``float``: an int or float, not a bool,
    finite unless the field is named in ``allow_inf`` (NaN never); ``bool``: only ``True``/``False`` (so YAML's
    ``"no"`` in quotes is rejected); ``str``: a string; ``X | None``: None or an X; ``Literal[...]``: one of the
    values; ``tuple[float, float]``: a list or tuple of exactly that many entries, each checked;
    ``tuple[int, ...]``: any length; a nested dataclass: an instance, or a mapping of its keys (unknown keys
    raise), checked recursively with dotted keys (``barrier.widths[2]``); any other class: an instance of it.
    Values are normalized in place: lists become tuples, numpy scalars and ints in float fields plain ``int``
    and ``float``, nested mappings configs, so the config is hashable and ``dataclasses.asdict`` of it is plain
    YAML data. Raises :class:`ConfigError` (a ``ValueError``) naming the key and the value, or ``TypeError``
    for an annotation it does not know (a bug in the config class, not in the user's value).
    """
    if not dataclasses.is_dataclass(config) or isinstance(config, type):
        raise TypeError(f"check_fields expects a dataclass instance, got {config!r}")
    hints = _hints(type(config))
    inf_ok = set(allow_inf)
    names = {f.name for f in dataclasses.fields(config)}
    if not inf_ok <= names:
        raise TypeError(f"check_fields: allow_inf names unknown fields {sorted(inf_ok - names)}")
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        checked = _check_value(f.name, hints[f.name], value, f.name in inf_ok)
        if checked is not value:
            object.__setattr__(config, f.name, checked)


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of the file ``path``, in hex: how a config names a file it loads (weights, a model), by content,
    never by where it lies."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


# --- fields added after results were recorded ---------------------------------------------------------------
def added_field(default: Any, *, neutral: Any, by_road: tuple = ()) -> Any:
    """A config field added after records were made without it. ``neutral``: its value that reproduces the behaviour
    from before it existed (it may differ from ``default``, the value new configs take). At its neutral value the
    field is left out of a config's hash (:func:`bimp.agents.evaluation.provenance.config_hash`), so the records made
    before it existed keep resuming; ``bimp migrate`` writes it into them at that value. A field whose old behaviour no
    value reproduces is declared as a plain field: it is always hashed, and the old records are refused, as they must
    be. ``by_road``: values that reproduce the neutral value's behaviour except where the env's road asks otherwise,
    and there the policy records what the road changed (its ``road``, hashed beside the config): left out of the hash
    too, so that a road that asks for nothing keeps its old records.

        gate_barriers: bool = added_field(True, neutral=True)
        road_guard: bool | None = added_field(None, neutral=False, by_road=(None,))
    """
    return dataclasses.field(default=default, metadata={"neutral": neutral, "by_road": tuple(by_road)})


def neutral_values(cls: type, by_road: bool = False) -> dict[str, Any]:
    """``{field: neutral value}`` of the fields of the config class ``cls`` declared with :func:`added_field`; a
    nested config's as a nested mapping (only where it has some). ``by_road``: ``{field: [neutral value, *by_road
    values]}``, every value left out of a config's hash."""
    hints = _hints(cls)
    out: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if "neutral" in f.metadata:
            neutral = f.metadata["neutral"]
            out[f.name] = [neutral, *f.metadata["by_road"]] if by_road else neutral
        elif isinstance(hints[f.name], type) and dataclasses.is_dataclass(hints[f.name]):
            nested = neutral_values(hints[f.name], by_road)
            if nested:
                out[f.name] = nested
    return out


__all__ = ["CONFIG_DIR", "TUNED_DIR", "TUNING_SUFFIX", "ConfigError", "added_field", "check_fields",
           "check_tuned_for", "file_sha256", "is_old_tuned", "load_config", "load_layered", "merged", "neutral_values",
           "read_overrides", "read_yaml", "renamed_key", "tuned_files", "tuning_path"]
