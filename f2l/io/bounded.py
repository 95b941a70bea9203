"""TOML and JSON from outside the program, read with bounds: size, nesting depth, string length,
and finite numbers.

Python's parsers recurse once per nesting level, so a 2-KB ``session.toml`` nested 1,000 tables
deep, or a record's ``meta_json`` nested 100,000 deep, ends in ``RecursionError``; ``tomllib`` and
``json`` also accept ``nan`` / ``NaN`` and ``inf``. :func:`load_toml` and :func:`load_json` refuse
all of these with :class:`InputError` ``("<source>: <reason>")`` before anything downstream sees
the data:

- JSON: the nesting depth is measured on the text (brackets outside strings, one vectorised pass)
  before parsing; TOML: parsed with the recursion caught, then measured on the result
  (iteratively);
- strings longer than :data:`MAX_STRING_CHARS`, texts over ``max_bytes`` and non-finite numbers
  are refused, naming the key path (``a/b/0/c``) of the first offender.
"""

from __future__ import annotations

import json
import math
import re
import tomllib
from typing import Any

import numpy as np

__all__ = ["InputError", "MAX_DEPTH", "MAX_STRING_CHARS", "MAX_TEXT_BYTES", "load_toml", "load_json",
           "check_tree", "json_depth"]

MAX_DEPTH = 32
"""Deepest nesting accepted (a session TOML uses 4 levels, a record's meta 3)."""
MAX_STRING_CHARS = 65536
"""Longest string value or key accepted."""
MAX_TEXT_BYTES = 16 * 2**20
"""Largest TOML/JSON text accepted by default (16 MiB)."""


class InputError(ValueError):
    """A TOML/JSON input that f2l refuses; the message is ``"<source>: <reason>"``."""


_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"', re.DOTALL)


def json_depth(text: str) -> int:
    """Deepest ``[``/``{`` nesting of a JSON text, strings skipped (no parsing, no recursion)."""
    bare = _JSON_STRING.sub('""', text)
    b = np.frombuffer(bare.encode("utf-8", "surrogatepass"), np.uint8)
    step = (np.isin(b, (ord("["), ord("{"))).astype(np.int32)
            - np.isin(b, (ord("]"), ord("}"))).astype(np.int32))
    return int(np.cumsum(step).max(initial=0))


def _where(path: tuple) -> str:
    return "/".join(map(str, path)) or "(top level)"


def check_tree(value: Any, source: str, *, max_depth: int = MAX_DEPTH,
               max_string: int = MAX_STRING_CHARS) -> None:
    """Walk a parsed value iteratively; :class:`InputError` for depth beyond ``max_depth``, a
    string or key longer than ``max_string``, or a float that is NaN or infinite."""
    stack: list[tuple[Any, tuple]] = [(value, ())]
    while stack:
        v, path = stack.pop()
        if len(path) > max_depth:
            raise InputError(f"{source}: nested deeper than {max_depth} levels (at {_where(path[:4])}/...)")
        if isinstance(v, dict):
            for k, item in v.items():
                if isinstance(k, str) and len(k) > max_string:
                    raise InputError(f"{source}: {_where(path)}: a key of {len(k)} characters "
                                     f"(at most {max_string})")
                stack.append((item, path + (k,)))
        elif isinstance(v, list):
            stack.extend((item, path + (i,)) for i, item in enumerate(v))
        elif isinstance(v, str):
            if len(v) > max_string:
                raise InputError(f"{source}: {_where(path)}: a string of {len(v)} characters "
                                 f"(at most {max_string})")
        elif isinstance(v, float) and not math.isfinite(v):
            raise InputError(f"{source}: {_where(path)}: {v!r} is not a finite number")


def _text(data: str | bytes, source: str, max_bytes: int) -> str:
    size = len(data)
    if size > max_bytes:
        raise InputError(f"{source}: {size} bytes, more than the {max_bytes} accepted")
    if isinstance(data, bytes):
        try:
            return data.decode("utf-8")
        except UnicodeDecodeError as exc:
            raise InputError(f"{source}: not UTF-8 text ({exc})") from None
    return data


def load_toml(data: str | bytes, source: str, *, max_depth: int = MAX_DEPTH,
              max_string: int = MAX_STRING_CHARS, max_bytes: int = MAX_TEXT_BYTES) -> dict:
    """Parse TOML text with bounds (module doc); :class:`InputError` naming ``source``."""
    text = _text(data, source, max_bytes)
    try:
        config = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{source}: not valid TOML ({exc})") from None
    except RecursionError:
        raise InputError(f"{source}: nested deeper than {max_depth} levels") from None
    check_tree(config, source, max_depth=max_depth, max_string=max_string)
    return config


def _no_constants(name: str):
    raise ValueError(f"{name} is not a finite number")


def load_json(data: str | bytes, source: str, *, max_depth: int = MAX_DEPTH,
              max_string: int = MAX_STRING_CHARS, max_bytes: int = MAX_TEXT_BYTES) -> Any:
    """Parse JSON text with bounds (module doc); :class:`InputError` naming ``source``.
    ``NaN``, ``Infinity`` and ``-Infinity`` are refused."""
    text = _text(data, source, max_bytes)
    depth = json_depth(text)
    if depth > max_depth:
        raise InputError(f"{source}: nested {depth} levels deep, more than the {max_depth} accepted")
    try:
        value = json.loads(text, parse_constant=_no_constants)
    except (json.JSONDecodeError, ValueError, RecursionError) as exc:
        raise InputError(f"{source}: not valid JSON ({exc})") from None
    check_tree(value, source, max_depth=max_depth, max_string=max_string)
    return value
