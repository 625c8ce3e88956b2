"""Typed configs: dataclasses, presets, ``--config FILE.yaml`` and ``--set key=value``.

A method's config is a dataclass whose fields are section dataclasses (by convention ``data``,
``train``, ``eval`` and ``deploy``). Keys are dotted paths (``train.lr``). A preset is a dict
of dotted overrides applied to the defaults; the config is then resolved as

    defaults  <-  preset  <-  --config file  <-  --set key=value (in order)

and every value is checked against its field's type: a ``Literal[...]`` field takes only its
choices, and a field made with ``field_(default, help, ge=..., gt=..., le=..., lt=...)`` only
values in that range. A section that needs a rule between its fields defines ``validate(self)``,
raising :class:`~physint_cli.errors.BadInput`; :func:`resolve` calls it once every value is set.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import types
import typing
from pathlib import Path
from typing import Any, Literal, Union, get_args, get_origin, get_type_hints

import yaml

from .errors import BadInput, suggest

PRESETS = ("tiny", "small", "paper")


def is_config(obj: Any) -> bool:
    return dataclasses.is_dataclass(obj)


def _hints(cls) -> dict[str, Any]:
    return get_type_hints(cls)


def flat_fields(cls, prefix: str = "") -> dict[str, tuple[Any, Any, str]]:
    """``{dotted key: (type, default, help)}`` for every leaf field of a config dataclass."""
    out: dict[str, tuple[Any, Any, str]] = {}
    instance = cls() if isinstance(cls, type) else cls
    hints = _hints(type(instance))
    for f in dataclasses.fields(instance):
        key = prefix + f.name
        value = getattr(instance, f.name)
        if dataclasses.is_dataclass(value):
            out.update(flat_fields(value, key + "."))
        else:
            out[key] = (hints[f.name], value, f.metadata.get("help", ""))
    return out


BOUNDS = {"ge": (">=", lambda v, b: v >= b), "gt": (">", lambda v, b: v > b),
          "le": ("<=", lambda v, b: v <= b), "lt": ("<", lambda v, b: v < b)}


def _field_bounds(cls) -> dict[str, dict[str, Any]]:
    """``{dotted key: {"ge": 1, ...}}`` for every leaf field that was given a range."""
    out: dict[str, dict[str, Any]] = {}
    instance = cls() if isinstance(cls, type) else cls
    for f in dataclasses.fields(instance):
        value = getattr(instance, f.name)
        if dataclasses.is_dataclass(value):
            out.update({f"{f.name}.{k}": v for k, v in _field_bounds(value).items()})
        elif f.metadata.get("bounds"):
            out[f.name] = f.metadata["bounds"]
    return out


def range_text(bounds: dict[str, Any]) -> str:
    """``>= 1`` or ``in [0, 1)`` for a field's bounds."""
    low = next(((k, bounds[k]) for k in ("ge", "gt") if k in bounds), None)
    high = next(((k, bounds[k]) for k in ("le", "lt") if k in bounds), None)
    if low and high:
        return f"in {'[' if low[0] == 'ge' else '('}{low[1]}, {high[1]}{']' if high[0] == 'le' else ')'}"
    k, b = low or high
    return f"{BOUNDS[k][0]} {b}"


def check_range(key: str, value: Any, bounds: dict[str, Any], source: str = "--set") -> None:
    """BadInput unless ``value`` lies in ``bounds`` (None passes: an optional field left unset)."""
    if value is None or not bounds:
        return
    values = value if isinstance(value, (list, tuple)) else (value,)
    for v in values:
        if not all(BOUNDS[k][1](v, b) for k, b in bounds.items()):
            raise BadInput(f"{source} {key}: must be {range_text(bounds)}, got {value!r}")


def type_name(tp: Any) -> str:
    origin = get_origin(tp)
    if origin is Literal:
        return "{" + ",".join(str(a) for a in get_args(tp)) + "}"
    if origin in (Union, types.UnionType):
        return " | ".join(type_name(a) for a in get_args(tp))
    if origin in (tuple, list):
        args = get_args(tp)
        if origin is tuple and len(args) == 2 and args[1] is Ellipsis:
            return f"tuple[{type_name(args[0])}, ...]"
        return f"{origin.__name__}[{', '.join(type_name(a) for a in args)}]"
    if tp is type(None):
        return "None"
    return getattr(tp, "__name__", str(tp))


def coerce(value: Any, tp: Any, key: str) -> Any:
    """Convert ``value`` (a YAML value or a ``--set`` string) to ``tp``, or raise BadInput."""
    origin = get_origin(tp)
    bad = BadInput(f"--set {key}: expected {type_name(tp)}, got {value!r}")
    if origin is Literal:
        choices = get_args(tp)
        for c in choices:
            if value == c or str(value) == str(c):
                return c
        raise BadInput(f"--set {key}: {value!r} is not one of {', '.join(map(str, choices))}{suggest(str(value), map(str, choices))}")
    if origin in (Union, types.UnionType):
        args = get_args(tp)
        if type(None) in args and (value is None or str(value).lower() in ("none", "null", "~")):
            return None
        for a in args:
            if a is type(None):
                continue
            try:
                return coerce(value, a, key)
            except BadInput:
                continue
        raise bad
    if origin in (tuple, list):
        items = value
        if isinstance(value, str):
            text = value.strip()
            try:
                items = yaml.safe_load(text if text.startswith("[") else f"[{text}]")
            except yaml.YAMLError:
                raise bad from None
        if not isinstance(items, (list, tuple)):
            raise bad
        args = get_args(tp)
        if origin is tuple and args and not (len(args) == 2 and args[1] is Ellipsis):
            if len(items) != len(args):
                raise BadInput(f"--set {key}: expected {len(args)} values, got {len(items)}")
            return tuple(coerce(v, a, key) for v, a in zip(items, args))
        inner = args[0] if args else Any
        converted = [coerce(v, inner, key) for v in items]
        return tuple(converted) if origin is tuple else converted
    if tp is bool:
        if isinstance(value, bool):
            return value
        text = str(value).lower()
        if text in ("1", "true", "yes", "on"):
            return True
        if text in ("0", "false", "no", "off"):
            return False
        raise bad
    if tp is int:
        if isinstance(value, bool):
            raise bad
        if isinstance(value, int):
            return value
        try:
            f = float(str(value).replace("_", ""))
        except ValueError:
            raise bad from None
        if not f.is_integer():
            raise bad
        return int(f)
    if tp is float:
        if isinstance(value, bool):
            raise bad
        try:
            return float(value)
        except (TypeError, ValueError):
            raise bad from None
    if tp is str:
        if isinstance(value, (dict, list)):
            raise bad
        return str(value)
    if tp is Any:
        return value
    raise bad


def valid_keys_message(cls) -> str:
    return "valid keys: " + ", ".join(flat_fields(cls))


def set_key(cfg: Any, key: str, raw: Any, source: str = "--set") -> None:
    """Set a dotted key on a config instance, type-checked."""
    fields = flat_fields(type(cfg))
    if key not in fields:
        raise BadInput(f"{source}: unknown key {key!r}{suggest(key, fields)}; {valid_keys_message(type(cfg))}")
    tp = fields[key][0]
    try:
        value = coerce(raw, tp, key)
    except BadInput as exc:
        raise BadInput(str(exc).replace("--set", source, 1)) from None
    check_range(key, value, _field_bounds(type(cfg)).get(key, {}), source)
    *parents, leaf = key.split(".")
    target = cfg
    for p in parents:
        target = getattr(target, p)
    setattr(target, leaf, value)


def validate(cfg: Any) -> Any:
    """Check a whole config: every field's range (defaults included), then each section's
    ``validate()`` (rules between fields). Returns ``cfg``; BadInput names the key."""
    for key, bounds in _field_bounds(type(cfg)).items():
        value = cfg
        for part in key.split("."):
            value = getattr(value, part)
        check_range(key, value, bounds, source="config")
    sections = [cfg] + [getattr(cfg, f.name) for f in dataclasses.fields(cfg) if dataclasses.is_dataclass(getattr(cfg, f.name))]
    for section in sections:
        check = getattr(section, "validate", None)
        if callable(check):
            check()
    return cfg


def parse_set(item: str) -> tuple[str, str]:
    if "=" not in item:
        raise BadInput(f"--set expects key=value, got {item!r}")
    key, value = item.split("=", 1)
    return key.strip(), value.strip()


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def load_file(path: str | Path) -> dict[str, Any]:
    """Read a YAML/JSON config file into flat dotted overrides."""
    p = Path(path)
    if not p.is_file():
        raise BadInput(f"--config {path}: no such file")
    try:
        data = yaml.safe_load(p.read_text()) or {}
    except yaml.YAMLError as exc:
        raise BadInput(f"--config {path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise BadInput(f"--config {path}: expected a mapping of keys to values")
    # a saved run/dataset config has the method's config under "config"
    if "config" in data and isinstance(data["config"], dict) and "method" in data:
        data = data["config"]
    return _flatten(data)


def resolve(cls, presets: dict[str, dict[str, Any]], preset: str = "small",
            config_file: str | Path | None = None, overrides: list[str] | None = None,
            skip_file_sections: tuple[str, ...] = ()) -> Any:
    """Build a config: defaults <- preset <- config file <- --set overrides.

    Keys of the config file under a top-level section in ``skip_file_sections`` are not read (a
    trained run's saved config fixes its data and model, not how it is evaluated or deployed).
    """
    if preset not in presets:
        raise BadInput(f"unknown preset {preset!r}{suggest(preset, presets)}; valid: {', '.join(presets)}")
    cfg = cls()
    for key, value in presets[preset].items():
        set_key(cfg, key, value, source=f"preset {preset}")
    if config_file:
        for key, value in load_file(config_file).items():
            if key.split(".", 1)[0] not in skip_file_sections:
                set_key(cfg, key, value, source=f"--config {config_file}")
    for item in overrides or []:
        key, value = parse_set(item)
        set_key(cfg, key, value)
    return validate(cfg)


def to_dict(cfg: Any) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


def from_dict(cls, data: dict[str, Any]) -> Any:
    """Rebuild a config saved with :func:`to_dict` (unknown keys are an error)."""
    cfg = cls()
    for key, value in _flatten(data).items():
        set_key(cfg, key, value, source="saved config")
    return validate(cfg)


def fingerprint(section: Any) -> str:
    """A short stable hash of a config (section), for cache keys."""
    blob = json.dumps(dataclasses.asdict(section) if dataclasses.is_dataclass(section) else section,
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:10]


def describe(cls, presets: dict[str, dict[str, Any]], preset: str) -> list[dict[str, str]]:
    """Rows for ``--help-config``: key, type, value under the preset, default, help."""
    resolved = resolve(cls, presets, preset)
    rows = []
    bounds = _field_bounds(cls)
    for key, (tp, default, help_text) in flat_fields(cls).items():
        value = resolved
        for part in key.split("."):
            value = getattr(value, part)
        kind = type_name(tp) + (f" {range_text(bounds[key])}" if key in bounds else "")
        rows.append({"key": key, "type": kind, "value": repr(value), "default": repr(default), "help": help_text})
    return rows


def field_(default: Any = dataclasses.MISSING, help: str = "", *, ge: Any = None, gt: Any = None,  # noqa: A002
           le: Any = None, lt: Any = None, **kw) -> Any:
    """A dataclass field with a help text shown by ``--help-config`` and, optionally, a range its
    values must lie in (``ge`` >=, ``gt`` >, ``le`` <=, ``lt`` <; each element of a tuple too),
    checked whenever the key is set and by :func:`validate`."""
    bounds = {k: v for k, v in (("ge", ge), ("gt", gt), ("le", le), ("lt", lt)) if v is not None}
    metadata = {"help": help, "bounds": bounds}
    if default is not dataclasses.MISSING and isinstance(default, (list, dict, set)):
        return dataclasses.field(default_factory=lambda d=default: typing.cast(Any, type(d)(d)), metadata=metadata, **kw)
    if default is not dataclasses.MISSING and dataclasses.is_dataclass(default):
        return dataclasses.field(default_factory=type(default), metadata=metadata, **kw)
    return dataclasses.field(default=default, metadata=metadata, **kw)
