"""Dataclasses <-> plain dicts / YAML, with clear errors for unknown or ill-typed keys.

The bottom layer of seqtrojan: it imports nothing from the package but :mod:`seqtrojan.errors`, so that any
module (the env included) can read its configuration without pulling in the rest. YAML presets in ``configs/``
and JSON model cards are read with :func:`from_dict`, which checks every key and value type and names the dotted
path of anything wrong; values in messages are truncated (:func:`short_repr`). YAML is read the 1.2 way, with
aliases refused (:func:`parse_yaml`).

Stage results (analysis, defense, detection, evaluation) are saved with :func:`to_dict` and loaded with
:func:`from_dict` too, so that a misspelt or missing key fails at load with its dotted path. Fields may be nested
dataclasses, tuples, lists, ``X | None`` and ``dict[str, X]``. A type that is saved in its own form defines
``serde_dump(self)`` (its plain form) and a classmethod ``serde_load(data, path)`` (back, raising ConfigError
with ``path``); :class:`seqtrojan.stats.Rate` does.
"""

from __future__ import annotations

import dataclasses
import json
import re
import reprlib
import types
import typing
from pathlib import Path
from typing import Any, Literal, TypeVar, Union, get_args, get_origin, get_type_hints

import yaml

from seqtrojan.errors import ConfigError

T = TypeVar("T")

__all__ = [
    "dump_omitting_defaults",
    "from_dict",
    "load_json",
    "load_yaml",
    "parse_yaml",
    "save_json",
    "short_repr",
    "to_dict",
]


def dump_omitting_defaults(obj: Any, optional: tuple[str, ...]) -> dict[str, Any]:
    """A dataclass's saved form (its ``serde_dump``) with the ``optional`` fields left out where they equal the
    defaults of ``type(obj)()``: fields added after files were first written, so that an old file reads as the
    same config."""
    defaults = type(obj)()
    return {
        f.name: to_dict(getattr(obj, f.name))
        for f in dataclasses.fields(obj)
        if f.name not in optional or getattr(obj, f.name) != getattr(defaults, f.name)
    }


def to_dict(obj: Any) -> Any:
    """A dataclass (nested) as plain dicts/lists, ready for YAML or JSON."""
    if not isinstance(obj, type) and hasattr(obj, "serde_dump"):
        return obj.serde_dump()
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [to_dict(x) for x in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


def save_json(obj: Any, path: str | Path) -> Path:
    """Write a dataclass (nested) as indented JSON (:func:`to_dict`); the file's parent folder must exist."""
    path = Path(path)
    path.write_text(json.dumps(to_dict(obj), indent=2))
    return path


def load_json(cls: type[T], path: str | Path) -> T:
    """The dataclass ``cls`` from a JSON file (:func:`from_dict`). A missing file, bad JSON, or a wrong, missing or
    ill-typed key is a ConfigError naming the file (and the key's dotted path)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except OSError as err:
        raise ConfigError(f"cannot read {str(path)!r}: {err.strerror or err}") from None
    except ValueError as err:
        raise ConfigError(f"{str(path)!r} is not valid JSON: {err}") from None
    try:
        return from_dict(cls, data, "")
    except ConfigError as err:
        raise ConfigError(f"{str(path)!r} is not a valid {cls.__name__}: {err}") from None


_REPR = reprlib.Repr()
_REPR.maxlevel, _REPR.maxlist, _REPR.maxtuple, _REPR.maxdict, _REPR.maxset = 3, 4, 4, 4, 4
_REPR.maxstring, _REPR.maxother, _REPR.maxlong = 60, 60, 40
_MAX_REPR = 80


def short_repr(value: Any) -> str:
    """``repr(value)`` for an error message, at most ~80 characters however large (or deeply shared) the value."""
    text = _REPR.repr(value)
    return text if len(text) <= _MAX_REPR else text[: _MAX_REPR - 3] + "..."


def from_dict(cls: type[T], data: Any, path: str = "") -> T:
    """Build dataclass ``cls`` from a (nested) dict, checking keys and value types."""
    if isinstance(data, cls):
        return data
    if not isinstance(data, dict):
        raise ConfigError(f"{path or cls.__name__} must be a mapping, got {type(data).__name__}: {short_repr(data)}")
    hints = get_type_hints(cls)
    fields = dataclasses.fields(cls)  # type: ignore[arg-type]
    names = {f.name for f in fields}
    where = f" in {path}" if path else ""
    unknown = sorted(set(data) - names)
    if unknown:
        raise ConfigError(f"unknown config key(s) {unknown}{where}; known keys: {sorted(names)}")
    required = {f.name for f in fields if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING}
    missing = sorted(required - set(data))
    if missing:
        raise ConfigError(f"missing key(s) {missing}{where} ({cls.__name__})")
    kwargs = {k: _convert(hints[k], v, f"{path}.{k}" if path else k) for k, v in data.items()}
    try:
        return cls(**kwargs)
    except TypeError as err:  # pragma: no cover - from_dict already checked the keys
        raise ConfigError(f"{path or cls.__name__}: {err}") from None


def _convert(tp: Any, value: Any, path: str) -> Any:
    origin = get_origin(tp)
    if tp is Any:
        return value
    if origin in (Union, types.UnionType):
        options = get_args(tp)
        if value is None and type(None) in options:
            return None
        tagged = [o for o in options if isinstance(o, type) and dataclasses.is_dataclass(o) and hasattr(o, "KIND")]
        if len(tagged) > 1:
            return _convert_tagged(tagged, value, path)
        errors = []
        for option in options:
            if option is type(None):
                continue
            try:
                return _convert(option, value, path)
            except ConfigError as err:
                errors.append(str(err))
        raise ConfigError(errors[0] if len(errors) == 1 else f"{path}: {short_repr(value)} matches none of {tp}")
    if origin is Literal:
        if value not in get_args(tp):
            raise ConfigError(f"{path}={short_repr(value)} is not one of {list(get_args(tp))}")
        return value
    if isinstance(tp, type) and hasattr(tp, "serde_load"):
        return tp.serde_load(value, path)
    if isinstance(tp, type) and dataclasses.is_dataclass(tp):
        return from_dict(tp, value, path)
    if origin in (dict, typing.Dict):  # noqa: UP006
        if not isinstance(value, dict):
            raise ConfigError(f"{path} must be a mapping, got {type(value).__name__}: {short_repr(value)}")
        key_tp, value_tp = get_args(tp) or (Any, Any)
        return {
            _convert(key_tp, k, f"{path} key {k!r}"): _convert(value_tp, v, f"{path}.{k}" if path else str(k))
            for k, v in value.items()
        }
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path} must be a list, got {type(value).__name__}: {short_repr(value)}")
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{path}[{i}]") for i, v in enumerate(value))
        if len(args) != len(value):
            raise ConfigError(f"{path} must have {len(args)} items, got {len(value)}: {short_repr(value)}")
        return tuple(_convert(a, v, f"{path}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if origin in (list, typing.List):  # noqa: UP006
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{path} must be a list, got {type(value).__name__}: {short_repr(value)}")
        (arg,) = get_args(tp)
        return [_convert(arg, v, f"{path}[{i}]") for i, v in enumerate(value)]
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{path} must be a number, got {short_repr(value)}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{path} must be an integer, got {short_repr(value)}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{path} must be true or false, got {short_repr(value)}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{path} must be a string, got {short_repr(value)}")
        return value
    return value


def _convert_tagged(options: list[Any], value: Any, path: str) -> Any:
    """A union of dataclasses that each name their ``KIND`` (a class attribute): the mapping's ``kind`` key picks
    the class; a mapping without one is the class whose ``KIND`` is listed first in the union (the section's
    original form, written before the union existed). The ``kind`` key is then read by that class as its field."""
    if not isinstance(value, dict):
        raise ConfigError(f"{path} must be a mapping, got {type(value).__name__}: {short_repr(value)}")
    kinds = {o.KIND: o for o in options}
    kind = value.get("kind", options[0].KIND)
    if not isinstance(kind, str) or kind not in kinds:
        raise ConfigError(f"{path}.kind={short_repr(kind)} is not one of {sorted(kinds)}")
    cls = kinds[kind]
    names = {f.name for f in dataclasses.fields(cls)}
    data = value if "kind" in names else {k: v for k, v in value.items() if k != "kind"}
    try:
        return from_dict(cls, data, path)
    except ConfigError as err:
        if "kind" in value:
            raise
        unknown = set(data) - names
        fits = [o.KIND for o in options if o is not cls and unknown <= {f.name for f in dataclasses.fields(o)}]
        if not unknown or not fits:
            raise
        raise ConfigError(f"{err} (a {fits[0]} section starts with kind: {fits[0]})") from None


MAX_YAML_DEPTH = 64
"""deepest nesting of mappings and lists in a YAML file (a config nests 5 or 6 deep; PyYAML composes recursively)"""


class _Yaml12Loader(yaml.SafeLoader):
    """PyYAML's safe loader read the YAML 1.2 way: only true/false are booleans, so that a key like ``off:`` (the
    OFF trigger) stays the string 'off' instead of becoming False as YAML 1.1 reads on/off/yes/no; and 1e-3 is a
    number, not a string.

    Aliases (``*name``, and so ``<<: *name`` merges) are refused: a few lines of nested aliases expand to billions
    of nodes (the "billion laughs"). Anchors alone are harmless and allowed. A key given twice in one mapping is
    refused (YAML 1.2 forbids it; PyYAML would keep the last silently), and so is nesting deeper than
    :data:`MAX_YAML_DEPTH` (before it could exhaust Python's recursion limit).
    """

    _depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            raise yaml.composer.ComposerError(
                None, None, f"found alias *{event.anchor}: aliases are not allowed in config files", event.start_mark
            )
        if self._depth >= MAX_YAML_DEPTH:
            mark = self.peek_event().start_mark
            raise yaml.composer.ComposerError(None, None, f"nested more than {MAX_YAML_DEPTH} deep", mark)
        self._depth += 1
        try:
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node)
            if key in seen:
                raise yaml.constructor.ConstructorError(
                    None, None, f"duplicate key {short_repr(key)}", key_node.start_mark
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


_Yaml12Loader.yaml_implicit_resolvers = {
    first: [(tag, regexp) for tag, regexp in resolvers if tag != "tag:yaml.org,2002:bool"]
    for first, resolvers in yaml.SafeLoader.yaml_implicit_resolvers.items()
}
_Yaml12Loader.add_implicit_resolver(
    "tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"), list("tTfF")
)


_Yaml12Loader.add_implicit_resolver(  # 1e-3 and 3E+4 are numbers (YAML 1.1 wants a dot: 1.0e-3)
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"), list("-+0123456789")
)


def parse_yaml(text: str) -> Any:
    """YAML text -> Python data, with YAML 1.2 booleans and no aliases (see :class:`_Yaml12Loader`)."""
    return yaml.load(text, Loader=_Yaml12Loader)


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping, with a clear error for a missing file or bad YAML."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {str(path)!r} does not exist")
    try:
        data = parse_yaml(path.read_text())
    except yaml.YAMLError as err:
        raise ConfigError(f"config file {str(path)!r} is not valid YAML: {_yaml_problem(err)}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"config file {str(path)!r} must hold a mapping at the top level")
    return data


def _yaml_problem(err: yaml.YAMLError) -> str:
    """A YAML error on one line: what is wrong and where (PyYAML's own text spans lines, with a caret)."""
    if isinstance(err, yaml.MarkedYAMLError) and err.problem:
        mark = err.problem_mark
        where = f" (line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        return f"{err.context + ': ' if err.context else ''}{err.problem}{where}"
    return " ".join(str(err).split())
