"""Node parameters as one frozen dataclass per node: declaration and validation rules (pure, no ROS).

A node's dataclass derives from :class:`NodeParameters`: a field per ROS parameter, named as the parameter (units in
the names), its default the declared default, its :func:`ros_parameter` metadata the descriptor. How a node
declares, checks and applies them: docs/architecture.md, "One pipeline each" (node parameters).
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import MISSING, Field, dataclass, field, fields, replace
import math
from typing import Any, TypeVar

SPEC_KEY = "ros_parameter"
P = TypeVar("P", bound="NodeParameters")


@dataclass(frozen=True)
class ParameterSpec:
    """How one parameter is declared: its descriptor (the range bounds are inclusive)."""

    description: str
    min_value: float | None = None
    max_value: float | None = None
    read_only: bool = False
    constraints: str = ""


def ros_parameter(default: Any, description: str, *, min_value: float | None = None,
                  max_value: float | None = None, read_only: bool = False, constraints: str = "") -> Any:
    """A dataclass field that is a ROS parameter: ``default`` (bool, int, float, str, a tuple of floats or a
    non-empty tuple of strings, which gives its ROS type) and its descriptor."""
    return field(default=default, metadata={SPEC_KEY: ParameterSpec(description, min_value, max_value, read_only,
                                                                    constraints)})


def _type_problem(name: str, default: Any, value: Any) -> str | None:
    """Why ``value`` is not of the type of ``default`` (an int is a float; a bool is no number), or None."""
    def number(v: Any) -> bool:
        return isinstance(v, (int, float)) and not isinstance(v, bool)

    if isinstance(default, bool):
        ok, want = isinstance(value, bool), "a bool"
    elif isinstance(default, int):
        ok, want = isinstance(value, int) and not isinstance(value, bool), "an integer"
    elif isinstance(default, float):
        ok, want = number(value), "a number"
    elif isinstance(default, str):
        ok, want = isinstance(value, str), "a string"
    elif isinstance(default, tuple) and _is_string_list(default):
        want = "a list of strings"
        try:
            ok = not isinstance(value, (str, bytes)) and all(isinstance(v, str) for v in value)
        except TypeError:
            ok = False
    elif isinstance(default, tuple):
        want = "a list of numbers"
        try:
            ok = not isinstance(value, (str, bytes)) and all(number(v) for v in value)
        except TypeError:
            ok = False
    else:  # pragma: no cover - a field declared with an unsupported default
        raise TypeError(f"parameter {name}: unsupported type {type(default).__name__}")
    return None if ok else f"{name} must be {want}, got {value!r}"


def _is_string_list(default: tuple) -> bool:
    """A tuple default of strings (a ROS string array; an empty tuple is a list of numbers)."""
    return bool(default) and all(isinstance(v, str) for v in default)


def _coerce(default: Any, value: Any) -> Any:
    """``value`` as the type of ``default`` (a float field stores a float, a list a tuple of floats or strings)."""
    if isinstance(default, float):
        return float(value)
    if isinstance(default, tuple):
        return tuple(str(v) for v in value) if _is_string_list(default) else tuple(float(v) for v in value)
    return value


@dataclass(frozen=True)
class NodeParameters:
    """Base of a node's parameter dataclass: declared parameters, checks and copies with new values."""

    @classmethod
    def specs(cls) -> Iterator[tuple[Field, ParameterSpec]]:
        """The fields that are ROS parameters and their descriptors, in declaration order."""
        for f in fields(cls):
            spec = f.metadata.get(SPEC_KEY)
            if spec is not None:
                yield f, spec

    @classmethod
    def spec(cls, name: str) -> ParameterSpec | None:
        """The descriptor of parameter ``name``, or None when it is none of this class's parameters."""
        f = cls.__dataclass_fields__.get(name)
        return None if f is None else f.metadata.get(SPEC_KEY)

    @classmethod
    def read_only_names(cls) -> frozenset[str]:
        """The parameters that can only be set at start-up (launch overrides, YAML)."""
        return frozenset(f.name for f, spec in cls.specs() if spec.read_only)

    @classmethod
    def problem(cls, name: str, value: Any) -> str | None:
        """Why ``value`` is not a valid value of parameter ``name`` (type, range, :meth:`rule`), or None.

        None for a name that is not one of this class's parameters (a node's other parameters)."""
        spec = cls.spec(name)
        if spec is None:
            return None
        f = cls.__dataclass_fields__[name]
        default = f.default if f.default is not MISSING else f.default_factory()  # type: ignore[misc]
        reason = _type_problem(name, default, value)
        if reason:
            return reason
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            lo = -math.inf if spec.min_value is None else spec.min_value
            hi = math.inf if spec.max_value is None else spec.max_value
            if not lo <= value <= hi:  # NaN too
                return f"{name} must be in [{spec.min_value}, {spec.max_value}], got {value!r}"
        return cls.rule(name, _coerce(default, value))

    @classmethod
    def rule(cls, name: str, value: Any) -> str | None:
        """A subclass's checks beyond type and range (``value`` already coerced to the field's type)."""
        return None

    @classmethod
    def change_problem(cls, name: str, value: Any) -> str | None:
        """Why parameter ``name`` cannot be changed to ``value`` while the node runs (read-only, or
        :meth:`problem`), or None: what a node's on-set callback refuses a change with."""
        spec = cls.spec(name)
        if spec is not None and spec.read_only:
            return f"{name} is read-only: set it at start-up (launch argument or YAML)"
        return cls.problem(name, value)

    def with_values(self: P, values: Mapping[str, Any]) -> P:
        """A copy with the given values (names of this class's fields; others ignored), each coerced to its
        field's type. Raises ValueError (``"parameter <why>"``) for a value :meth:`problem` refuses."""
        known: dict[str, Any] = {}
        for name, value in values.items():
            f = self.__dataclass_fields__.get(name)
            if f is None:
                continue
            reason = self.problem(name, value)
            if reason:
                raise ValueError(f"parameter {reason}")
            known[name] = _coerce(f.default, value) if SPEC_KEY in f.metadata else value
        return replace(self, **known)

    def ros_values(self) -> dict[str, Any]:
        """``{name: value}`` of the declared parameters (tuples as lists, as ROS takes them)."""
        return {f.name: list(v) if isinstance(v := getattr(self, f.name), tuple) else v for f, _ in self.specs()}
