"""YAML presets turned into frozen dataclasses; unknown keys are errors.

Descriptor presets live in each method's folder, ``presets.yaml`` beside its
class (``lidar_iris_eval/descriptors/lidar_iris/presets.yaml``; an external
method's beside its module)::

    presets:
      paper: {key: value, ...}
      reference: {key: value, ...}
    sensors:            # optional per-sensor overrides on top of a preset
      vlp16:
        paper: {key: value}

Defaults are the dataclass defaults; a preset only lists what it changes.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import numbers
from pathlib import Path
from typing import Any, TypeVar

import yaml

from lidar_iris_eval.errors import LirisError, read_text

CONFIG_DIR = Path(__file__).resolve().parent / "configs"

P = TypeVar("P")

#: rule ``integer-parameter-range``: a size, count or iteration parameter above this
#: would only allocate terabytes or run for days; it is a typo, refused before any work
MAX_INTEGER_PARAMETER = 10**7
#: seeds are exempt from that bound but must fit NumPy's generators: 0 <= seed < 2**64
MAX_SEED = 2**64 - 1


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping, reporting a missing or malformed file as a LirisError."""
    path = Path(path)
    if not path.is_file():
        raise LirisError(path, "config file not found")
    try:
        data = yaml.safe_load(read_text(path, "config file"))
    except yaml.YAMLError as err:
        raise LirisError(path, f"not valid YAML ({str(err).splitlines()[0]})") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise LirisError(path, "expected a mapping at the top level")
    return data


def make_params(params_type: type[P], values: dict[str, Any], source: str) -> P:
    """Build a frozen params dataclass from ``values``, rejecting unknown keys.

    Values are converted to the type of the field's default (so YAML ``4`` works
    for a float field, and lists become tuples), keeping params hashable. A
    conversion that would change the value is refused, not done silently:
    ``rings=2.5`` for an integer field, a NaN or infinite number, a number
    given as text.
    """
    fields = {f.name: f for f in dataclasses.fields(params_type)}
    values = _renamed_keys(params_type, values, source)
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise LirisError(
            source,
            f"unknown config key(s) {', '.join(unknown)}; valid: {', '.join(sorted(fields))}",
        )
    converted = {}
    for key, value in values.items():
        default = fields[key].default
        try:
            converted[key] = _coerce(value, default)
            _check_integer_range(key, converted[key], default)
        except (TypeError, ValueError) as err:
            reason = f": {err}" if str(err) else ""
            raise LirisError(source, f"bad value {value!r} for {key}{reason}") from None
    return params_type(**converted)


def _renamed_keys(params_type: type, values: dict[str, Any], source: str) -> dict[str, Any]:
    """Old parameter spellings (``params_type.renamed``: old -> new) mapped to the new
    ones with a deprecation warning; both spellings at once is an error."""
    renamed = getattr(params_type, "renamed", None) or {}
    if not any(old in values for old in renamed):
        return values
    from lidar_iris_eval.errors import warn

    out = dict(values)
    for old, new in renamed.items():
        if old in out:
            if new in out:
                raise LirisError(source, f"{old} and {new} are the same parameter; give {new}")
            warn(source, f"parameter {old} is deprecated; use {new} (the old spelling goes in "
                         f"the next release)")
            out[new] = out.pop(old)
    return out


def _check_integer_range(key: str, value: Any, default: Any) -> None:
    """Rule ``integer-parameter-range`` (see :data:`MAX_INTEGER_PARAMETER`)."""
    if isinstance(default, bool) or not isinstance(default, int) or not isinstance(value, int):
        return
    if key == "seed" or key.endswith("_seed"):
        if not 0 <= value <= MAX_SEED:
            raise ValueError("a seed must be between 0 and 2**64 - 1")
    elif abs(value) > MAX_INTEGER_PARAMETER:
        raise ValueError(f"beyond {MAX_INTEGER_PARAMETER:,} (rule integer-parameter-range)")


def _coerce(value: Any, default: Any) -> Any:
    if value is None and default is not None and default is not dataclasses.MISSING:
        raise ValueError("no value given")
    if default is dataclasses.MISSING or default is None or value is None:
        return tuple(value) if isinstance(value, list) else value
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise TypeError
        return value
    if isinstance(default, (int, float)):
        if isinstance(value, bool) or not isinstance(value, numbers.Real):
            raise TypeError(f"expected a number, got {type(value).__name__}")
        if not math.isfinite(value):
            raise ValueError("must be a finite number")
        if isinstance(default, int) and value != int(value):
            raise ValueError("must be a whole number")
        return type(default)(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise TypeError(f"expected text, got {type(value).__name__}")
        return value
    if isinstance(default, tuple):
        return tuple(value)
    return value


def params_dict(params: Any) -> dict[str, Any]:
    """A plain, JSON-serialisable dict of a params dataclass."""
    values = dataclasses.asdict(params)
    return {k: list(v) if isinstance(v, tuple) else v for k, v in values.items()}


def params_hash(params: Any) -> str:
    """A short stable hash of a params dataclass, for cache keys."""
    text = json.dumps(params_dict(params), sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def descriptor_preset_values(
    name: str, preset: str | None, sensor: str | None = None, path: Path | None = None
) -> tuple[str, dict[str, Any]]:
    """Values of a descriptor's preset (plus sensor overrides) from its YAML file.

    Returns ``(preset_name, values)``. ``preset=None`` picks the file's first preset.
    ``path`` is the method's own ``presets.yaml`` (in its folder), when it has one;
    otherwise ``<package>/configs/descriptors/<name>.yaml`` if present (no method ships
    one there any more; without a file the preset is ``default`` with no values).
    """
    path = CONFIG_DIR / "descriptors" / f"{name}.yaml" if path is None else Path(path)
    if not path.is_file():
        return preset or "default", {}
    data = load_yaml(path)
    presets = data.get("presets") or {}
    if preset is None:
        preset = next(iter(presets), "default")
    if preset not in presets:
        raise LirisError(
            f"--preset {preset}", f"unknown preset for {name}; choose from {', '.join(presets)}"
        )
    values = dict(presets[preset] or {})
    if sensor:
        sensors = data.get("sensors") or {}
        overrides = (sensors.get(sensor) or {}).get(preset) or {}
        values.update(overrides)
    return preset, values


# --- strict schemas for YAML/JSON files liris reads back ------------------------------


class AnyMapping:
    """Schema leaf: a mapping whose keys are not checked (e.g. descriptor parameters)."""


class OneOf:
    """Schema leaf: one of ``choices``, or a value accepted by ``accept``."""

    def __init__(self, *choices: Any, accept=None, text: str = ""):
        self.choices = choices
        self.accept = accept
        self.text = text or ", ".join(map(str, choices))


_TYPE_NAMES = {str: "text", int: "a whole number", float: "a number", bool: "true/false",
               type(None): "null", list: "a list", dict: "a mapping"}


def _type_ok(value: Any, kind: type) -> bool:
    if kind is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if kind is int:
        return isinstance(value, int) and not isinstance(value, bool)
    return isinstance(value, kind)


def check_schema(value: Any, schema: Any, source: str | Path, where: str = "") -> None:
    """Raise one LirisError naming ``source`` and the key path when ``value`` breaks ``schema``.

    ``schema`` is a type (``str``, ``int``, ``float`` for any number, ``bool``), a
    tuple of alternatives (``(int, None)``), a dict (a mapping with exactly those
    optional keys: unknown keys are errors, as in ``--plan`` files), a
    one-element list (a list of that schema), :class:`AnyMapping` or :class:`OneOf`.
    """
    label = where or "top level"
    if isinstance(schema, tuple):
        errors = []
        for option in schema:
            try:
                check_schema(value, type(None) if option is None else option, source, where)
                return
            except LirisError as err:
                errors.append(err.problem.split(": ", 1)[-1])
        raise LirisError(source, f"{label}: expected {' or '.join(_describe(o) for o in schema)}, "
                                 f"got {value!r}")
    if isinstance(schema, dict):
        if not isinstance(value, dict):
            raise LirisError(source, f"{label}: expected a mapping, got {value!r}")
        unknown = sorted(str(k) for k in set(value) - set(schema))
        if unknown:
            raise LirisError(source, f"{label}: unknown key(s) {', '.join(unknown)}; valid: "
                                     f"{', '.join(sorted(schema))}")
        for key, item in value.items():
            check_schema(item, schema[key], source, f"{where}.{key}" if where else str(key))
        return
    if isinstance(schema, list):
        if not isinstance(value, list):
            raise LirisError(source, f"{label}: expected a list, got {value!r}")
        for k, item in enumerate(value):
            check_schema(item, schema[0], source, f"{label}[{k}]")
        return
    if schema is AnyMapping:
        if not isinstance(value, dict):
            raise LirisError(source, f"{label}: expected a mapping, got {value!r}")
        return
    if isinstance(schema, OneOf):
        if value in schema.choices or (schema.accept is not None and schema.accept(value)):
            return
        raise LirisError(source, f"{label}: {value!r} is not valid; choose {schema.text}")
    if not _type_ok(value, schema):
        raise LirisError(source, f"{label}: expected {_describe(schema)}, got {value!r}")
    if schema is float and not math.isfinite(value):
        raise LirisError(source, f"{label}: must be a finite number, got {value!r}")


def _describe(schema: Any) -> str:
    if schema is None:
        return "null"
    if isinstance(schema, dict) or schema is AnyMapping:
        return "a mapping"
    if isinstance(schema, list):
        return "a list"
    if isinstance(schema, OneOf):
        return f"one of {schema.text}"
    return _TYPE_NAMES.get(schema, getattr(schema, "__name__", str(schema)))
