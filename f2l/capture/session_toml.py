"""What a session's ``session.toml`` says, and where the files it names are (the "session TOML"
and "hostile input" parts of :mod:`f2l.capture.ingest`'s conventions).

- :func:`load_session_toml`: the TOML read with bounds (:func:`f2l.io.bounded.load_toml`) and
  validated against schema ``session``; an invalid one is a reason naming the file and key.
- :func:`view_for`, :func:`matched_shot`, :func:`unmatched_globs`, :func:`key_where`: the lens,
  pose and role a file gets from the first ``[[shots]]`` glob it matches.
- :func:`resolve_session_file`, :func:`regular_file`, :func:`outside_target`: a file the TOML
  names (a flat field) resolved inside the session folder; absolute paths, ``..`` and symbolic
  links out of it are refused unless allowed.
- :func:`shown_path`, :func:`is_utf8`: file names as they are printed and stored.
"""

from __future__ import annotations

import fnmatch
from collections import Counter
import os
import stat as stat_mod
from pathlib import Path


SESSION_TOML = "session.toml"


def outside_target(base: str, path: Path) -> str | None:
    """The resolved target of ``path`` when it lies outside the folder whose real path is
    ``base`` (a symbolic link out of the capture tree), else None."""
    real = os.path.realpath(path)
    return None if os.path.commonpath([base, real]) == base else real


def load_session_toml(folder: Path) -> tuple[dict, str]:
    """(config, problem): the folder's session.toml, read with bounds (:func:`f2l.io.bounded.load_toml`:
    size, nesting depth, string length, finite numbers) and validated against schema ``session``;
    ({}, "") when there is none, ({}, reason naming the file and key) when it is invalid."""
    import jsonschema

    from f2l.io.bounded import MAX_TEXT_BYTES, InputError, load_toml
    from f2l.io.schema import load_schema

    path = folder / SESSION_TOML
    if not path.is_file():
        return {}, ""
    shown = shown_path(path)
    try:
        with open(path, "rb") as fh:
            data = fh.read(MAX_TEXT_BYTES + 1)  # load_toml refuses more than MAX_TEXT_BYTES
        config = load_toml(data, shown)
        jsonschema.validate(config, load_schema("session"))
    except InputError as exc:
        return {}, str(exc)
    except OSError as exc:
        return {}, f"{shown}: cannot be read ({exc.strerror or exc})"
    except jsonschema.ValidationError as exc:
        where = "/".join(str(p) for p in exc.absolute_path) or "(top level)"
        return {}, f"{shown}: {where}: {exc.message}{_toml_hint(exc)}"
    return config, ""


def shown_path(path: str | os.PathLike) -> str:
    """A path as valid UTF-8 text: bytes of a file name that are not UTF-8 (Python holds them as
    surrogate escapes) shown as ``\\xff``."""
    text = os.fspath(path)
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        return os.fsencode(text).decode("utf-8", "backslashreplace")


def is_utf8(text: str) -> bool:
    try:
        text.encode("utf-8")
        return True
    except UnicodeEncodeError:
        return False


def matched_shot(config: dict, rel_in_session: str) -> int | None:
    """Index of the first ``[[shots]]`` entry whose ``files`` glob matches, None when none does."""
    for i, shot in enumerate(config.get("shots", [])):
        if fnmatch.fnmatch(rel_in_session, shot["files"]):
            return i
    return None


def key_where(config: dict, shot: int | None, key: str) -> str:
    """Where a view's lens key comes from in the session TOML: ``shots/<i>/<key>`` when the
    matched shot sets it, else ``lens/<key>`` (the key as given when neither does)."""
    if shot is not None and key in config.get("shots", [])[shot]:
        return f"shots/{shot}/{key}"
    if key in config.get("lens", {}):
        return f"lens/{key}"
    return key or "lens"


def unmatched_globs(config: dict, rels_in_session: list[str]) -> list[str]:
    """"shots/<i>/files = '<glob>': ..." for each ``[[shots]]`` glob that matches none of the
    session's files, or whose files all an earlier shot already took (first match wins)."""
    shots = config.get("shots", [])
    taken = Counter(matched_shot(config, rel) for rel in rels_in_session)
    out = []
    for i, shot in enumerate(shots):
        if taken[i]:
            continue
        glob = shot["files"]
        if any(fnmatch.fnmatch(rel, glob) for rel in rels_in_session):
            out.append(f"shots/{i}/files = {glob!r}: every file it matches is taken by an earlier shot "
                       f"(the first match wins); the shot applies to no file")
        else:
            out.append(f"shots/{i}/files = {glob!r} matches no file of the session (globs match paths relative "
                       f"to the session folder, e.g. 'sky/*'); the shot applies to no file")
    return out


def session_files(config: dict) -> list[tuple[str, str]]:
    """(key path, file name) of every file a session TOML names: ``lens/falloff/file`` and
    ``shots/<i>/falloff/file``."""
    out = []
    for where, table in [("lens", config.get("lens", {}))] + [
            (f"shots/{i}", shot) for i, shot in enumerate(config.get("shots", []))]:
        falloff = table.get("falloff")
        if isinstance(falloff, dict) and falloff.get("file"):
            out.append((f"{where}/falloff/file", str(falloff["file"])))
    return out


class OutsideError(ValueError):
    """A path named in a session TOML that leaves the session folder."""


def resolve_session_file(folder: Path, name: str, *, allow_outside: bool = False) -> tuple[Path, bool]:
    """(path, outside) of a file named in ``folder``'s session TOML, relative to ``folder``:
    OutsideError for an absolute path, a ``..`` that leaves the folder or a symlink (the file or a
    folder above it inside the session) that resolves outside it, unless ``allow_outside``
    (then ``outside`` says whether it does)."""
    from pathlib import PurePosixPath, PureWindowsPath

    absolute = (PurePosixPath(name).is_absolute() or PureWindowsPath(name).is_absolute()
                or bool(PureWindowsPath(name).drive))
    path = Path(name) if absolute else folder / name
    base = os.path.realpath(folder)
    real = os.path.realpath(path)
    inside = not absolute and os.path.commonpath([base, real]) == base
    if inside or allow_outside:
        return path, not inside
    if absolute:
        raise OutsideError(f"{name!r} is an absolute path; files named in a session.toml must be inside the "
                           f"session folder")
    if os.path.normpath(name).split(os.sep)[0] == os.pardir:
        raise OutsideError(f"{name!r} leaves the session folder {shown_path(folder)}")
    raise OutsideError(f"{name!r} resolves to {shown_path(real)} through a symbolic link, outside the session "
                       f"folder {shown_path(base)}")


def regular_file(path: Path) -> str:
    """"" when ``path`` is a readable regular file, else why not (missing, a folder, a FIFO, ...)."""
    try:
        st = os.stat(path)
    except OSError as exc:
        return "not found" if isinstance(exc, FileNotFoundError) else f"cannot be read ({exc.strerror or exc})"
    if not stat_mod.S_ISREG(st.st_mode):
        return "not a regular file"
    return ""


_TOP_LEVEL_KEYS = ("probe_azimuth_deg", "timezone", "lens", "shots")


def _toml_hint(exc) -> str:
    """Why a top-level key can land inside a table: TOML gives a key after ``[[shots]]`` or
    ``[lens]`` to that table."""
    path = list(exc.absolute_path)
    stray = [k for k in _TOP_LEVEL_KEYS if f"'{k}'" in exc.message]
    if path and path[0] in ("shots", "lens") and stray:
        return (f" ({stray[0]} is a top-level key: in TOML a key written after a [{path[0]}] table belongs to "
                f"that table; move it above the first table)")
    return ""


def view_for(config: dict, rel_in_session: str) -> dict:
    """What the session TOML says about one file (lens defaults, first matching shot)."""
    view = {}
    lens = config.get("lens", {})
    view.update({k: v for k, v in lens.items()})
    if "probe_azimuth_deg" in config:
        view["probe_azimuth_deg"] = config["probe_azimuth_deg"]
    shot = matched_shot(config, rel_in_session)
    if shot is not None:
        view.update({k: v for k, v in config["shots"][shot].items() if k != "files"})
    return view
