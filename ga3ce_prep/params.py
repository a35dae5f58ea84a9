"""Typed parameter dataclasses: one field per line with its default, and its unit and reason in a
trailing comment, the way `synthetic/config.py` and nanoGPT's `GPTConfig` keep them.

    @dataclass(frozen=True, kw_only=True)
    class Params:
        min_depth: float = param(0.1, minimum=0)  # metres; nearer sensor values count as unknown

Everything else is derived from that one declaration:
- `field_docs(cls)`: each field's trailing comment (the CLI's help, the schema's descriptions);
- `json_schema(cls)`: the JSON Schema of the dataclass (types from the annotations, defaults,
  required fields, the comment as `description`, and the JSON Schema keywords given to `param`);
- `from_dict(cls, values, where)`: an instance from a pipeline file's mapping; an unknown or
  missing key is a ConfigError naming `where.key`;
- `defaults(cls)`: the defaults as plain JSON values.

`load_yaml` reads the files and `--set` values those mappings come from.
"""
from __future__ import annotations

import ast
import dataclasses
import functools
import inspect
import io
import re
import textwrap
import tokenize
import types
import typing
from pathlib import Path
from typing import Any, Literal

import yaml

from .errors import ConfigError


def param(default: Any = dataclasses.MISSING, *, file: str | None = None, hint: str | None = None,
          **schema: Any) -> Any:
    """A dataclass field with its default and extra JSON Schema keywords (`minimum`,
    `exclusiveMinimum`, `maximum`, `minItems`, `items`, ...). `file="model"` or `"data"` marks a
    path parameter (`x-file`: resolved against the --data root, checked before any work) and
    `hint` says how to make the file (`x-hint`, shown when it is missing). No default: required."""
    meta = dict(schema)
    if file is not None:
        meta["x-file"] = file
    if hint is not None:
        meta["x-hint"] = hint
    return dataclasses.field(default=default, metadata={"schema": meta})


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """The trailing comment of each field of a dataclass and of its dataclass bases (comments on
    the lines the field's declaration spans), by field name."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            src = textwrap.dedent(inspect.getsource(klass))
        except (OSError, TypeError):
            continue
        comments = {t.start[0]: t.string.lstrip("#").strip()
                    for t in tokenize.generate_tokens(io.StringIO(src).readline) if t.type == tokenize.COMMENT}
        class_def = ast.parse(src).body[0]
        assert isinstance(class_def, ast.ClassDef)  # the source of a class
        for node in class_def.body:
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                end = node.end_lineno or node.lineno  # always set by ast.parse
                text = " ".join(comments[i] for i in range(node.lineno, end + 1) if i in comments)
                if text:
                    docs[node.target.id] = text
    return docs


def _jsonable(value: Any) -> Any:
    if isinstance(value, tuple | list):
        return [_jsonable(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    return value


def _type_schema(tp: Any) -> dict[str, Any]:
    """JSON Schema of a field annotation: bool, int, float, str, Path, Literal[...], tuple[X, ...],
    and X | None."""
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Literal:
        return {"enum": list(args)}
    if origin in (types.UnionType, typing.Union):
        inner = [a for a in args if a is not type(None)]
        if len(inner) != 1:
            raise TypeError(f"unsupported parameter type {tp}")
        spec = _type_schema(inner[0])
        if "type" in spec:
            spec["type"] = [spec["type"], "null"]
        else:
            spec["enum"] = [*spec["enum"], None]
        return spec
    if origin is tuple:
        if len(args) != 2 or args[1] is not Ellipsis:
            raise TypeError(f"tuple parameters must be tuple[X, ...], not {tp}")
        return {"type": "array", "items": _type_schema(args[0])}
    simple = {bool: "boolean", int: "integer", float: "number", str: "string", Path: "string"}
    if tp in simple:
        return {"type": simple[tp]}
    raise TypeError(f"unsupported parameter type {tp}")


def _has_default(f: dataclasses.Field) -> bool:
    return f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING


def _default(f: dataclasses.Field) -> Any:
    """The default of a field that has one (_has_default): its default, or its factory's value."""
    if f.default_factory is dataclasses.MISSING:
        return f.default
    return f.default_factory()


def json_schema(cls: type) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a parameter dataclass; unknown keys are refused."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    props: dict[str, Any] = {}
    required = []
    for f in dataclasses.fields(cls):
        spec = _type_schema(hints[f.name])
        if _has_default(f):
            spec["default"] = _jsonable(_default(f))
        else:
            required.append(f.name)
        if f.name in docs:
            spec["description"] = docs[f.name]
        extra = dict(f.metadata.get("schema", {}))
        if "items" in extra and "items" in spec:
            extra["items"] = {**spec["items"], **extra["items"]}
        spec.update(extra)
        props[f.name] = spec
    out: dict[str, Any] = {"type": "object", "additionalProperties": False, "properties": props}
    if required:
        out["required"] = required
    return out


def defaults(cls: type) -> dict[str, Any]:
    """The fields that have defaults, as plain JSON values (tuples as lists)."""
    return {f.name: _jsonable(_default(f)) for f in dataclasses.fields(cls) if _has_default(f)}


def file_fields(cls: type) -> dict[str, dict[str, Any]]:
    """Path parameters (`param(file=...)`): name -> {"x-file": "model" | "data", "x-hint": ...}."""
    return {f.name: f.metadata["schema"] for f in dataclasses.fields(cls)
            if "x-file" in f.metadata.get("schema", {})}


def from_dict(cls: type, values: dict[str, Any], where: str = "params") -> Any:
    """An instance of the dataclass from a mapping (lists become tuples for tuple fields, file
    parameters become Paths); ConfigError naming `where.key` for an unknown or missing key."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - set(fields))
    if unknown:
        raise ConfigError(f"{where}.{unknown[0]}: unknown parameter; known: {', '.join(fields)}")
    missing = [n for n, f in fields.items() if not _has_default(f) and n not in values]
    if missing:
        raise ConfigError(f"{where}.{missing[0]}: required parameter is missing")
    hints = typing.get_type_hints(cls)
    files = file_fields(cls)
    kw = {}
    for name, value in values.items():
        if isinstance(value, list) and typing.get_origin(hints[name]) is tuple:
            value = tuple(value)
        elif name in files and isinstance(value, str):
            value = Path(value)
        kw[name] = value
    return cls(**kw)


class _Yaml12Loader(yaml.SafeLoader):
    """SafeLoader with YAML 1.2's booleans: only true/false (any case), so `off`, `on`, `yes` and `no`
    stay strings, as the parameters' enums spell them (`reuse: off`, `io_binding: on`)."""


_Yaml12Loader.yaml_implicit_resolvers = {k: [(tag, rx) for tag, rx in v if tag != "tag:yaml.org,2002:bool"]
                                         for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_Yaml12Loader.add_implicit_resolver("tag:yaml.org,2002:bool", re.compile(r"^(?:true|True|TRUE|false|False|FALSE)$"),
                                    list("tTfF"))


def load_yaml(text: str | bytes) -> Any:
    """Parse a pipeline or config file, or a `--set` value, with YAML 1.2's booleans (`_Yaml12Loader`)."""
    return yaml.load(text, Loader=_Yaml12Loader)


__all__ = ["defaults", "field_docs", "file_fields", "from_dict", "json_schema", "load_yaml", "param"]
