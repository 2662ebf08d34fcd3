"""Checks of scene-file values.

Each raises :class:`warpfem.errors.InputError` with one line naming the file, the table, the key and what is wrong.
"""

from __future__ import annotations

import math
import operator
import re

from warpfem.errors import InputError

_NAME_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class _Problem:
    """Builds the one-line error messages of one table of one scene file."""

    def __init__(self, origin: str, prefix: str):
        self.origin = origin
        self.prefix = prefix

    def __call__(self, key: str, problem: str) -> InputError:
        return InputError(f"{self.origin}: {self.prefix}{key} {problem}".replace("\n", " "))


def _table(origin: str, name: str) -> _Problem:
    """The error builder for a plain table: keys read ``solver.cg_mode``."""
    return _Problem(origin, f"{name}.")


def _object_table(origin: str, index: int, name: object) -> _Problem:
    """The error builder for ``object[index]``: keys read ``object[0] 'bunny': young``."""
    label = f"object[{index}] '{name}'" if isinstance(name, str) and name else f"object[{index}]"
    return _Problem(origin, f"{label}: ")


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _shown(value: object) -> str:
    """A value as the user wrote it, with its type when that is the problem."""
    if isinstance(value, str):
        return f'"{value}" (a string)'
    if isinstance(value, bool):
        return f"{str(value).lower()} (a boolean)"
    if isinstance(value, dict):
        return "a table"
    return repr(value)


def _check_int(err: _Problem, key: str, value: object, lo: int, hi: int | None = None) -> None:
    if not isinstance(value, int) or isinstance(value, bool):
        raise err(key, f"must be an integer, got {_shown(value)}")
    if value < lo or (hi is not None and value > hi):
        bound = f">= {lo}" if hi is None else f"in {lo}..{hi}"
        raise err(key, f"must be {bound}, got {value}")


def _check_float(err: _Problem, key: str, value: object) -> None:
    if not _is_number(value):
        raise err(key, f"must be a number, got {_shown(value)}")
    if not math.isfinite(value):
        raise err(key, f"must be finite, got {value}")


def _check_range(
    err: _Problem,
    key: str,
    value: object,
    unit: str = "",
    *,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
) -> None:
    """Check a finite number against the bounds given (``gt``: >, ``ge``: >=, ``lt``: <, ``le``: <=)."""
    _check_float(err, key, value)
    checks = [(">", gt, operator.gt), (">=", ge, operator.ge), ("<", lt, operator.lt), ("<=", le, operator.le)]
    checks = [(op, bound, holds) for op, bound, holds in checks if bound is not None]
    if not all(holds(value, bound) for _, bound, holds in checks):
        bounds = " and ".join(f"{op} {bound:g}" for op, bound, _ in checks)
        suffix = f" {unit}" if unit else ""
        raise err(key, f"must be {bounds}{suffix}, got {value}")


def _check_vec3(err: _Problem, key: str, value: object) -> None:
    if not isinstance(value, (list, tuple)) or len(value) != 3 or not all(_is_number(v) for v in value):
        raise err(key, f"must be a list of 3 numbers, got {_shown(value)}")
    if not all(math.isfinite(v) for v in value):
        raise err(key, f"must hold finite numbers, got {list(value)}")


def _check_choice(err: _Problem, key: str, value: object, choices: tuple[str, ...]) -> None:
    if value not in choices or not isinstance(value, str):
        allowed = " or ".join(f'"{c}"' for c in choices)
        raise err(key, f"must be {allowed}, got {_shown(value)}")
