"""Settings with their valid ranges: a dataclass field made by `rule` carries its range in
its metadata (`FieldRule`), which the config checks read (`mbrl_delan.conf.checks`). The
bottom floor: the planners' settings, the models' and the config schemas use it, and a
builder refuses a bad value with `ConfigError`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from omegaconf import MISSING, ListConfig


def check_choice(path: str, value: Any, choices: Sequence[str]) -> None:
    """A `ConfigError` naming `path` and the valid `choices` unless `value` is one of them."""
    if value not in choices:
        raise ConfigError(f"{path}={value!r} is not valid; choose one of: {', '.join(choices)}")


class ConfigError(ValueError):
    """A config value is invalid; the message names it and the valid choices."""


def rule(
    default: Any = MISSING,
    *,
    low: float | None = None,
    high: float | None = None,
    above: bool = False,
    below: bool = False,
    choices: tuple[str, ...] | None = None,
    nonempty: bool = False,
) -> Any:
    """A dataclass field with its valid range: low <= value <= high (strict with `above` /
    `below`) or a value among `choices` (a list's rule: each element's; `nonempty`: at least
    one); None is always allowed for an Optional field."""
    meta = {"low": low, "high": high, "above": above, "below": below, "choices": choices,
            "nonempty": nonempty}  # fmt: skip
    return field(
        default=default,
        metadata={k: v for k, v in meta.items() if v is not None and v is not False},
    )


@dataclass
class FieldRule:
    """The range of one field, read from its metadata (see `rule`)."""

    low: float = -math.inf
    high: float = math.inf
    above: bool = False
    below: bool = False
    choices: tuple[str, ...] | None = None
    nonempty: bool = False

    def describe(self, value: Any = 0.0) -> str:
        """What a valid value is, in words (`value`: an int is described as a whole number)."""
        if self.nonempty and isinstance(value, list | tuple | ListConfig) and not value:
            return "give at least one value (or null)"
        if self.choices:
            return "choose one of: " + ", ".join(self.choices)
        parts = []
        if self.low > -math.inf:
            parts.append(f"{'>' if self.above else '>='} {self.low:g}")
        if self.high < math.inf:
            parts.append(f"{'<' if self.below else '<='} {self.high:g}")
        kind = "a whole number" if isinstance(value, int) else "a finite number"
        return f"it must be {kind}" + (" " + " and ".join(parts) if parts else "")

    def allows(self, value: Any) -> bool:
        if isinstance(value, list | tuple | ListConfig):  # a list: each element
            return bool(value or not self.nonempty) and all(self.allows(v) for v in value)
        if self.choices:
            return value in self.choices
        if isinstance(value, bool) or not isinstance(value, int | float):
            return True  # strings, lists, mappings: typed by the schema only
        if not math.isfinite(value):
            return False
        low_ok = value > self.low if self.above else value >= self.low
        high_ok = value < self.high if self.below else value <= self.high
        return low_ok and high_ok


def field_rule(metadata: Any) -> FieldRule:
    return FieldRule(**dict(metadata))
