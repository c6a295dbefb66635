"""Checked reading of TOML files written by people (profiles, model files, scenarios).

Check, then process: a :class:`TomlDoc` is read once; code takes values out of its :class:`Table` views
with typed getters. A bad value does not stop the reading: it is recorded with the file, the line where
it can be found, the key path, the value and what was expected, and a neutral placeholder is returned
so every other problem is found in the same pass. :meth:`TomlDoc.raise_problems` then raises one error
listing them all. Keys nobody asked for are reported as unknown, with a did-you-mean.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

from gateway.errors import GatewayError, did_you_mean, expected_one_of

_MISSING: Any = object()
_HEADER = re.compile(r"^\s*\[\[?\s*([^\]]+?)\s*\]\]?\s*(#.*)?$")
_KEYLINE = re.compile(r"^\s*([A-Za-z0-9_\-\"'. ]+?)\s*=")
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
_INLINE_KEY = re.compile(r"(?:^|[{,])\s*([A-Za-z0-9_\-]+)\s*=")


_MAX_DIGITS = 4300  # sys.get_int_max_str_digits() by default since Python 3.11


def _long_integer_line(text: str) -> str:
    """The line of the first integer too long to convert, for the message ('' when there is none)."""
    match = re.search(rf"\d[\d_]{{{_MAX_DIGITS},}}", text)
    return str(text.count("\n", 0, match.start()) + 1) if match else ""


def _split_dotted(text: str) -> tuple[str, ...]:
    parts = [p.strip().strip("\"'") for p in re.findall(r"\"[^\"]*\"|'[^']*'|[^.]+", text)]
    return tuple(p for p in parts if p)


def describe(value: Any) -> str:
    """Show a value the way the user wrote it, with its TOML type."""
    kind = {bool: "a boolean", int: "an integer", float: "a number", str: "a string",
            list: "an array", dict: "a table"}.get(type(value), type(value).__name__)
    if isinstance(value, dict):
        return "a table"
    shown = f'"{value}"' if isinstance(value, str) else repr(value)
    if len(shown) > 80:  # a 4000-digit integer or a 100 kB string: its start and its size say enough
        shown = f"{shown[:40]}... ({len(shown)} characters)"
    return f"{shown} ({kind})"


class TomlDoc:
    """A parsed TOML file plus the problems found while reading it."""

    def __init__(self, path: str | Path, *, error: type[GatewayError], text: str | None = None) -> None:
        self.path = Path(path)
        self.error = error
        self.problems: list[str] = []
        if text is None:
            try:
                text = self.path.read_text(encoding="utf-8-sig")
            except FileNotFoundError:
                raise error(f"{self.path}: file not found") from None
            except (OSError, UnicodeDecodeError) as exc:
                raise error(f"{self.path}: cannot read: {exc}") from None
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise error(f"{self.path}: not valid TOML: {exc}") from None
        except RecursionError:  # tomllib recurses once per level of nesting
            raise error(f"{self.path}: arrays or inline tables nested too deep to read: expected a few levels "
                        "(a profile or model nests at most three)") from None
        except ValueError as exc:  # an integer longer than Python converts (sys.get_int_max_str_digits)
            where = _long_integer_line(text)
            if not where:
                raise error(f"{self.path}: not valid TOML: {exc}") from None
            raise error(f"{self.path}:{where}: an integer of more than {_MAX_DIGITS} digits: expected "
                        f"an integer of at most {_MAX_DIGITS} digits") from None
        self._lines = self._index_lines(text)
        self.root = Table(self, data, ())

    @staticmethod
    def _index_lines(text: str) -> dict[tuple[str, ...], int]:
        """Map key paths to the line (1-based) that defines them: best effort, for messages only.

        Entries of an array of tables (``[[path]]``) and of an array of inline tables written one per line
        (``term = [`` then ``{ ... },`` lines) are numbered from 1, as :class:`Table` paths name them.
        """
        index: dict[tuple[str, ...], int] = {}
        counts: dict[tuple[str, ...], int] = {}  # array-of-tables key path -> entries so far
        prefix: tuple[str, ...] = ()
        array: tuple[str, ...] | None = None  # inside a multi-line array of inline tables
        for number, line in enumerate(text.splitlines(), start=1):
            stripped = line.strip()
            if stripped.startswith("#"):
                continue
            if array is not None:
                if stripped.startswith("{"):
                    counts[array] = counts.get(array, 0) + 1
                    entry = (*array, str(counts[array]))
                    index.setdefault(entry, number)
                    for key in _INLINE_KEY.findall(stripped):
                        index.setdefault((*entry, key), number)
                    continue
                if stripped.startswith("]"):
                    array = None
                    continue
            header = _HEADER.match(line)
            if header:
                prefix = ()
                parts = _split_dotted(header.group(1))
                for i, part in enumerate(parts):
                    prefix = (*prefix, part)
                    if i == len(parts) - 1 and stripped.startswith("[["):
                        counts[prefix] = counts.get(prefix, 0) + 1
                        index.setdefault(prefix, number)
                    if prefix in counts:
                        prefix = (*prefix, str(counts[prefix]))
                index.setdefault(prefix, number)
                continue
            key = _KEYLINE.match(line)
            if key:
                path = prefix + _split_dotted(key.group(1))
                index.setdefault(path, number)
                if stripped.endswith("["):
                    array = path
        return index

    def where(self, path: Sequence[str]) -> str:
        """``file:line: key.path`` for a message (the line of the key, else of its nearest table)."""
        path = tuple(path)
        for cut in range(len(path), -1, -1):
            line = self._lines.get(path[:cut])
            if line is not None:
                break
        loc = f"{self.path}:{line}" if line is not None else f"{self.path}"
        return f"{loc}: {'.'.join(path)}" if path else loc

    def problem(self, path: Sequence[str], message: str) -> None:
        # one line per problem, whatever a value or a quoted key holds (a multi-line string, a NUL)
        self.problems.append(_CONTROL.sub(lambda m: repr(m.group())[1:-1], f"{self.where(path)}: {message}"))

    def raise_problems(self) -> None:
        if self.problems:
            raise self.error("\n".join(self.problems))


class Table:
    """A view on one TOML table that remembers which keys were read."""

    def __init__(self, doc: TomlDoc, data: dict[str, Any], path: tuple[str, ...]) -> None:
        self.doc = doc
        self.data = data
        self.path = path
        self._taken: set[str] = set()

    # -- plumbing ---------------------------------------------------------------------------------------
    def __contains__(self, key: str) -> bool:
        return key in self.data

    def keys(self) -> list[str]:
        return list(self.data)

    def __iter__(self) -> Iterator[str]:
        return iter(list(self.data))

    def problem(self, key: str | None, message: str) -> None:
        self.doc.problem(self.path + ((key,) if key else ()), message)

    def _get(self, key: str, default: Any, expected: str) -> Any:
        self._taken.add(key)
        if key in self.data:
            return self.data[key]
        if default is _MISSING:
            self.problem(None, f'missing required key "{key}" (expected {expected})')
        return _MISSING

    def _bad(self, key: str, value: Any, expected: str, hint: str = "") -> None:
        self.problem(key, f"expected {expected}, got {describe(value)}{hint}")

    # -- typed getters ----------------------------------------------------------------------------------
    def str(self, key: str, *, default: Any = _MISSING, choices: Iterable[str] | None = None,
            expected: str | None = None, pattern: re.Pattern[str] | None = None) -> Any:
        """A string; with ``choices`` one of them (did-you-mean on a near miss)."""
        choices = list(choices) if choices is not None else None
        if expected is None:
            expected = expected_one_of(choices) if choices else "a string"
        value = self._get(key, default, expected)
        if value is _MISSING:
            return default if default is not _MISSING else None
        if not isinstance(value, str):
            self._bad(key, value, expected)
            return None
        if choices is not None and value not in choices:
            self._bad(key, value, expected, did_you_mean(value, choices))
            return None
        if pattern is not None and not pattern.fullmatch(value):
            self._bad(key, value, expected)
            return None
        return value

    def float(self, key: str, *, default: Any = _MISSING, min: float | None = None,
              max: float | None = None, min_exclusive: bool = False, expected: str | None = None,
              allow_inf: bool = False) -> Any:
        """A number (integers accepted), finite unless ``allow_inf``, within the given bounds."""
        if expected is None:
            expected = "a number" + _bounds_text(min, max, min_exclusive)
        value = self._get(key, default, expected)
        if value is _MISSING:
            return default if default is not _MISSING else None
        if isinstance(value, bool) or not isinstance(value, int | float) or not _fits_float(value):
            self._bad(key, value, expected)
            return None
        number = float(value)
        if math.isnan(number) or (math.isinf(number) and not allow_inf):
            self._bad(key, value, expected)
            return None
        if (min is not None and (number < min or (min_exclusive and number == min))) or (
            max is not None and number > max
        ):
            self._bad(key, value, expected)
            return None
        return number

    def int(self, key: str, *, default: Any = _MISSING, min: int | None = None, max: int | None = None,
            expected: str | None = None) -> Any:
        if expected is None:
            expected = "an integer" + _bounds_text(min, max, False)
        value = self._get(key, default, expected)
        if value is _MISSING:
            return default if default is not _MISSING else None
        if isinstance(value, bool) or not isinstance(value, int):
            self._bad(key, value, expected)
            return None
        if (min is not None and value < min) or (max is not None and value > max):
            self._bad(key, value, expected)
            return None
        return value

    def bool(self, key: str, *, default: Any = _MISSING) -> Any:
        value = self._get(key, default, "true or false")
        if value is _MISSING:
            return default if default is not _MISSING else None
        if not isinstance(value, bool):
            self._bad(key, value, "true or false")
            return None
        return value

    def str_list(self, key: str, *, default: Any = _MISSING, choices: Iterable[str] | None = None,
                 unique: bool = True, min_len: int = 0) -> Any:
        """An array of strings; each one of ``choices`` when given."""
        choices = list(choices) if choices is not None else None
        expected = "an array of strings" + (f" from {expected_one_of(choices)}" if choices else "")
        value = self._get(key, default, expected)
        if value is _MISSING:
            return default if default is not _MISSING else None
        if not isinstance(value, list) or not all(isinstance(v, str) for v in value):
            self._bad(key, value, expected)
            return None
        if len(value) < min_len:
            self._bad(key, value, f"{expected} with at least {min_len} entr{'y' if min_len == 1 else 'ies'}")
            return None
        for v in value:
            if choices is not None and v not in choices:
                self.problem(key, f'"{v}" is not allowed: expected {expected_one_of(choices)}'
                             f"{did_you_mean(v, choices)}")
                return None
        if unique and len(set(value)) != len(value):
            dup = sorted({v for v in value if value.count(v) > 1})
            self.problem(key, f"entries must be unique, got {', '.join(repr(d) for d in dup)} twice")
            return None
        return tuple(value)

    def float_list(self, key: str, *, default: Any = _MISSING, expected: str = "an array of numbers") -> Any:
        value = self._get(key, default, expected)
        if value is _MISSING:
            return default if default is not _MISSING else None
        if not isinstance(value, list) or not all(
            isinstance(v, int | float) and not isinstance(v, bool) and _fits_float(v) and math.isfinite(v)
            for v in value
        ):
            self._bad(key, value, expected)
            return None
        return tuple(float(v) for v in value)

    def raw(self, key: str, *, default: Any = _MISSING, expected: str = "a value") -> Any:
        """The value as parsed, for callers that check it themselves."""
        value = self._get(key, default, expected)
        return (default if default is not _MISSING else None) if value is _MISSING else value

    def table(self, key: str, *, required: bool = False, expected: str = "a table") -> Table | None:
        """A sub-table (``[a.b]``); ``None`` when absent and not required."""
        value = self._get(key, _MISSING if required else None, expected)
        if value is None or value is _MISSING:
            return None
        if not isinstance(value, dict):
            self._bad(key, value, expected)
            return None
        return Table(self.doc, value, (*self.path, key))

    def tables(self, key: str, *, required: bool = False, expected: str = "a table of tables",
               name_pattern: re.Pattern[str] | None = None) -> list[tuple[str, Table]]:
        """Named sub-tables (``[factors.speed]``, ``[factors.i1]``) in file order."""
        outer = self.table(key, required=required, expected=expected)
        if outer is None:
            return []
        out = []
        for name in outer:
            outer._taken.add(name)
            value = outer.data[name]
            if not isinstance(value, dict):
                outer.problem(name, f"expected a table [{'.'.join((*outer.path, name))}], got {describe(value)}")
                continue
            if name_pattern is not None and not name_pattern.fullmatch(name):
                outer.problem(name, f'bad name "{name}": expected letters, digits and "_", '
                                    "starting with a letter")
                continue
            out.append((name, Table(self.doc, value, (*outer.path, name))))
        return out

    def done(self) -> None:
        """Report every key that was never read as unknown, with a did-you-mean."""
        for key in self.data:
            if key not in self._taken:
                known = sorted(self._taken)
                hint = did_you_mean(key, known) or (
                    f" (expected one of: {', '.join(known)})" if known else " (this table takes no keys)"
                )
                self.problem(key, f"unknown key{hint}")


def _fits_float(value: int | float) -> bool:
    """Whether a TOML number converts to a float (an integer beyond 1.8e308 does not)."""
    return isinstance(value, float) or abs(value) < 2**1024


def _bounds_text(lo: float | None, hi: float | None, lo_exclusive: bool) -> str:
    if lo is not None and hi is not None:
        return f" in {'(' if lo_exclusive else '['}{lo:g}, {hi:g}]"
    if lo is not None:
        return f" {'>' if lo_exclusive else '>='} {lo:g}"
    if hi is not None:
        return f" <= {hi:g}"
    return ""


def check_each(items: Iterable[tuple[str, Table]], parse: Callable[[str, Table], Any]) -> list[Any]:
    """Parse every named table with ``parse``, keeping those that came back non-``None``."""
    return [r for r in (parse(name, t) for name, t in items) if r is not None]


NAME = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
