"""Option values converted without pydantic where the conversion is plain (Typer 0.29).

Typer 0.29 converts every command-line value through a pydantic ``TypeAdapter``; importing
pydantic for it was ~45 ms of CPU in every command's start-up, on the critical path of ``infer``
(its main process plans and hands out the chunks only after parsing). :func:`install` wraps
Typer's converter builder: a value that is plainly of its option's type (a ``str``, a ``bool``
flag, an ``int`` spelled as ASCII digits, a decimal ``float``, one of an enumeration's names, a
path string) is converted directly, to the very value Typer's own converter returns
(``tests/test_cli.py`` compares the two on every option of every command); anything else — an
error, a bound, a custom parser, a spelling such as ``1_000`` — goes to Typer's converter, which
then imports pydantic and answers as before, error messages included.

Only the Typer release line it was tested on (:data:`TESTED_TYPER`) is wrapped: the wrap uses Typer's private
converter API, so any other release runs untouched (and its start-up imports pydantic again).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from enum import Enum
from pathlib import Path
from typing import Any, Callable

TESTED_TYPER = "0.29."  # the Typer release line whose private converter builder this wraps; others run untouched
_INT = re.compile(r"[+-]?[0-9]+")  # no blanks, underscores or fractions: those go to pydantic
_FLOAT = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


class _NotPlain(Exception):
    """The value needs Typer's own converter."""


def _plain_str(value: Any) -> str:
    if isinstance(value, str):
        return value
    raise _NotPlain


def _plain_bool(value: Any) -> bool:
    if isinstance(value, bool):
        return value
    raise _NotPlain


def _plain_int(value: Any) -> int:
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    if isinstance(value, str) and _INT.fullmatch(value):
        return int(value)
    raise _NotPlain


def _plain_float(value: Any) -> float:
    if isinstance(value, float):
        return value
    if isinstance(value, str) and _FLOAT.fullmatch(value):
        return float(value)
    raise _NotPlain


def _leaf(descriptor: Any) -> Callable[[Any, Any, Any], Any] | None:
    """The direct converter ``(value, param, ctx) -> value`` of a single value of ``descriptor``'s
    type, or None where Typer's own is needed (bounds, custom parsers, dates, other types)."""
    from typer._param_types import coerce_cli_choice, coerce_cli_path, lenient_issubclass, routes_to_path

    info, annotation = descriptor.parameter_info, descriptor.annotation
    if info.parser is not None or descriptor.file_annotation is not None:
        return None
    if lenient_issubclass(annotation, Enum):
        choices = list(annotation)

        def choice(value: Any, param: Any, ctx: Any) -> Any:
            try:
                return coerce_cli_choice(value, choices=choices, case_sensitive=info.case_sensitive, ctx=ctx)
            except ValueError:  # Typer's converter words the error
                raise _NotPlain from None

        return choice
    if annotation is str:
        return lambda value, param, ctx: _plain_str(value)
    if annotation is bool:
        return lambda value, param, ctx: _plain_bool(value)
    if annotation in (int, float):
        if info.min is not None or info.max is not None or info.clamp:
            return None
        plain = _plain_int if annotation is int else _plain_float
        return lambda value, param, ctx: plain(value)
    if routes_to_path(annotation, info):
        path_type = info.path_type
        if path_type is None and lenient_issubclass(annotation, Path):
            path_type = annotation
        if not (path_type is None or path_type in (str, bytes) or path_type is Path):
            return None

        def path(value: Any, param: Any, ctx: Any) -> Any:
            if path_type is Path:  # pydantic's Path of a string is Path(string)
                value = Path(_plain_str(value)) if not isinstance(value, Path) else value
            return coerce_cli_path(value, info, path_type=path_type, param=param, ctx=ctx)

        return path
    return None


def _make_plain_param(runtime_param: type, original: Callable[[Any], Any]) -> type:
    @dataclass(frozen=True)
    class PlainRuntimeParam(runtime_param):  # type: ignore[misc,valid-type]
        """Converts plain values directly, the rest with Typer's converter (built on first need)."""

        descriptor: Any = None
        leaf: Any = None
        many: bool = False
        _typer: dict[str, Any] = field(default_factory=dict)

        def _fallback(self) -> Any:
            if "rp" not in self._typer:
                self._typer["rp"] = original(self.descriptor)
            return self._typer["rp"]

        def _coerce_value(self, value: Any, param: Any, ctx: Any) -> Any:
            try:
                if self.many:
                    if not isinstance(value, (list, tuple)):
                        raise _NotPlain
                    return [self.leaf(v, param, ctx) for v in value]
                return self.leaf(value, param, ctx)
            except _NotPlain:
                return self._fallback()._coerce_value(value, param=param, ctx=ctx)

    return PlainRuntimeParam


def install() -> bool:
    """Make Typer convert plain option values without pydantic; True if installed (Typer 0.29.x),
    False on another Typer release line than :data:`TESTED_TYPER` or where Typer has no pydantic converter
    to spare (then nothing changes). Idempotent."""
    import typer

    if not typer.__version__.startswith(TESTED_TYPER):  # the wrap reads Typer's private converter API
        return False
    try:
        import typer.core as core
        from typer._coercion import RuntimeParam
        from typer._typing import get_args
    except ImportError:
        return False
    original = getattr(core, "build_runtime_param", None)
    if original is None:
        return False
    if getattr(original, "plain_values", False):
        return True
    plain_param = _make_plain_param(RuntimeParam, original)

    def build_runtime_param(descriptor: Any) -> Any:
        many = bool(descriptor.is_list)
        if many:
            args = get_args(descriptor.annotation)
            if len(args) != 1:
                return original(descriptor)
            leaf = _leaf(type(descriptor)(args[0], descriptor.parameter_info, descriptor.file_annotation))
        elif descriptor.is_tuple:
            return original(descriptor)
        else:
            leaf = _leaf(descriptor)
        if leaf is None:
            return original(descriptor)
        return plain_param(
            parameter_info=descriptor.parameter_info,
            annotation=descriptor.annotation,
            descriptor=descriptor,
            leaf=leaf,
            many=many,
        )

    build_runtime_param.plain_values = True  # type: ignore[attr-defined]
    core.build_runtime_param = build_runtime_param
    return True
