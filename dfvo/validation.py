"""Checks of typed settings, shared by every config schema of the package (one home for them).

The settings are dataclasses (the ``*Config`` classes; Hydra fills them from YAML and the command line), and each
checks its values in ``__post_init__`` with these helpers, so every bad value ends in the same one-line message that
names the setting by its full key (``tracker.scale.method='fast'; expected one of ['simple', 'iterative']``):

- :func:`choice`: a value as a member of a ``StrEnum`` (the choices of a setting are a ``StrEnum``; a plain ``str``
  field is validated with it when OmegaConf cannot hold the enum, e.g. values such as ``6dof`` that are not Python
  names).
- :func:`one_of`: the same for a setting whose choices are a tuple of strings (file formats).
- :func:`check`: raise a ``ValueError`` with the message unless the condition holds.
- :func:`positive`: the first of several values that is set and not > 0.
- :func:`typed`: a config node (Hydra's, or a plain dict such as a checkpoint's stored config) as its dataclass
  instance, which runs those checks; OmegaConf's own errors (unknown key, wrong type, missing value) become one line.

This module imports nothing from dfvo, so every layer (geometry up to the command line) can use it.
"""

from __future__ import annotations

from enum import Enum, StrEnum
from typing import Any, TypeVar

__all__ = ["choice", "choices", "one_of", "check", "positive", "typed"]

E = TypeVar("E", bound=StrEnum)


def choices(enum: type[StrEnum]) -> list[str]:
    """The allowed values of a setting whose choices are ``enum``, in declaration order."""
    return [m.value for m in enum]


def choice(enum: type[E], value: object, setting: str) -> E:
    """``value`` (a member of ``enum`` or its value) as the member.

    Raises:
        ValueError: ``SETTING=VALUE; expected one of [...]`` when it is not one of the enum's values.
    """
    try:
        return enum(value.value if isinstance(value, Enum) else value)
    except ValueError:
        raise ValueError(f"{setting}={value!r}; expected one of {choices(enum)}") from None


def one_of(allowed: tuple[str, ...] | list[str], value: object, setting: str) -> str:
    """``value`` when it is one of the strings ``allowed`` (for choices kept as a tuple of names, e.g. file formats).

    Raises:
        ValueError: ``SETTING=VALUE; expected one of [...]`` (the same message as :func:`choice`).
    """
    if value not in allowed:
        raise ValueError(f"{setting}={value!r}; expected one of {list(allowed)}")
    return str(value)


def check(condition: bool, message: str) -> None:
    """Raise ``ValueError(message)`` unless ``condition`` holds (``message`` names the setting and what is
    expected)."""
    if not condition:
        raise ValueError(message)


def positive(where: str, **values: float | None) -> None:
    """Raise ``WHERE.KEY=VALUE; expected > 0`` for the first value that is not None and not positive."""
    for key, value in values.items():
        if value is not None and not value > 0:
            raise ValueError(f"{where}.{key}={value}; expected > 0")


def _one_line(err: Exception, where: str) -> str:
    key = getattr(err, "full_key", None)
    msg = str(getattr(err, "msg", None) or err).splitlines()[0].strip()
    if key:
        return f"{where}.{key}: {msg}" if where else f"{key}: {msg}"
    return f"{where}: {msg}" if where and not msg.startswith(f"{where}.") else msg


def typed(node: Any, schema: type | None = None, where: str = "") -> Any:
    """A config node as its dataclass instance, validated by the dataclass' ``__post_init__``.

    Args:
        node: a node composed by Hydra (typed by its schema), or a plain dict / untyped node (e.g. a config stored in
            a checkpoint, a ``data`` node built in Python), which is merged into ``schema`` first.
        schema: the dataclass of the node (None: the node's own type).
        where: the node's key for messages (``"model"``).

    Raises:
        ValueError: one line naming the setting (unknown key, wrong type, missing value, failed check).
    """
    from omegaconf import DictConfig, OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    try:
        if not isinstance(node, DictConfig):
            node = OmegaConf.create(node)
        if schema is not None and OmegaConf.get_type(node) is not schema:
            node = OmegaConf.merge(OmegaConf.structured(schema), node)
        return OmegaConf.to_object(node)
    except OmegaConfBaseException as err:
        cause = err.__cause__ if isinstance(err.__cause__, ValueError) else None
        raise ValueError(str(cause) if cause else _one_line(err, where)) from err
