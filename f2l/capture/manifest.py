"""The incremental ingest run: scan → (reuse or read) rows → sessions, roles, brackets →
``WORK/captures.parquet`` (atomic). See :mod:`f2l.capture.ingest` for what each column means and
how hostile input (bad lens values, paths out of the session, globs that match nothing, file
names that are not UTF-8) is reported."""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path

from f2l.capture import brackets as br
from f2l.capture import ingest as ing
from f2l.capture import session_toml as st
from f2l.capture.view_spec import ViewSpec, ViewSpecError
from f2l.io.hashing import file_sha256
from f2l.io.progress import Progress, ProgressCallback

TABLE_NAME = "captures.parquet"


def _previous(table_path: Path) -> dict[str, dict]:
    """Rows of an earlier run by path ({} when there is none or it cannot be read)."""
    import pyarrow.parquet as pq

    from f2l.io.schema import validate_table
    from f2l.io.tables import table_row

    if not table_path.is_file():
        return {}
    try:
        table = pq.read_table(table_path)
        validate_table(table, "captures", source=str(table_path))
    except Exception:  # a damaged or older table: every file is read again
        return {}
    out = {}
    for i in range(table.num_rows):
        row = table_row(table, i)
        row["black_levels"] = [float(v) for v in row["black_levels"]]
        out[row["path"]] = row
    return out


def _new_row(rel: str, kind: str, stat: os.stat_result | None) -> dict:
    return {"path": rel, "sha256": "", "size_bytes": int(stat.st_size) if stat else 0,
            "mtime_ns": int(stat.st_mtime_ns) if stat else 0, "kind": kind, "session": "", "role": "other",
            "role_source": "none", "bracket_id": None, "status": "ok", "message": "",
            "view_json": ViewSpec().to_json(), "session_problem": "", "ingest_version": ing.INGEST_VERSION,
            **ing._empty_meta()}


def _read_row(path: Path, rel: str, kind: str, stat: os.stat_result) -> dict:
    row = _new_row(rel, kind, stat)
    try:
        row.update(ing.read_file_meta(path, kind))
        row["sha256"] = file_sha256(path)
    except Exception as exc:  # bad input never stops the ingest: the row says why
        msg = str(exc)
        row.update(status="error", message=msg if msg.startswith(str(path)) else f"{path}: {msg}")
    return row


def _unusable_row(path: Path, rel: str, stat: os.stat_result | None, why: str) -> dict:
    """An ``error`` row for a file that is not opened: ``why`` names it (``rel`` already shown as
    UTF-8)."""
    row = _new_row(rel, ing.kind_of(path), stat)
    row.update(status="error", message=why)
    return row


OUTSIDE_LINK = "symlink points outside the capture tree"


def _scan_item(root: Path, path: Path, previous: dict, allow_outside: bool = False,
               base: str | None = None) -> tuple:
    """(path, relative path as UTF-8, stat or None, reusable previous row or None, why the file is
    not opened or None) of one scanned file. ``base``: the capture root's real path. A symbolic
    link out of the tree is not opened unless ``allow_outside``; a previous row of it is reused
    only if that run read it (so a run with and one without ``allow_outside`` share no row)."""
    rel = path.relative_to(root).as_posix()
    shown = st.shown_path(rel)
    why = None
    try:
        stat = path.stat()
    except OSError as exc:  # a dangling symlink, a symlink loop, a file removed while scanning
        stat, why = None, f"{st.shown_path(path)}: cannot be read ({exc.strerror or exc})"
    target = st.outside_target(base or os.path.realpath(root), path) if why is None else None
    if target is not None and not allow_outside:
        why = (f"{st.shown_path(path)}: {OUTSIDE_LINK} (to {st.shown_path(target)}); the file is not read "
               f"(--allow-outside allows it)")
    if not st.is_utf8(rel):
        why = (f"{st.shown_path(path)}: the file name is not valid UTF-8 ({ascii(os.fsencode(rel))}); "
               f"the file is not read: rename it to ingest it")
    if why is not None:
        return path, shown, stat, None, why
    old = previous.get(rel)
    if target is not None and old is not None and not old["sha256"]:
        old = None  # refused (or unreadable) before: read it now that it is allowed
    return path, rel, stat, old if _unchanged(old, stat) else None, None


CONTENT_ROLES = ("face", "chart", "other")


def _unchanged(old: dict | None, stat: os.stat_result) -> bool:
    return (old is not None and old["size_bytes"] == stat.st_size
            and old["mtime_ns"] == stat.st_mtime_ns
            and old["ingest_version"] == ing.INGEST_VERSION)


def run_ingest(root: str | os.PathLike, work: str | os.PathLike, *,
               session_gap_min: float = 30.0, bracket_gap_s: float = 15.0,
               detect_roles: bool = True, progress: ProgressCallback | None = None, workers: int | None = None,
               allow_outside: bool = False) -> ing.IngestSummary:
    """Ingest the tree under ``root`` into ``work/captures.parquet``; returns counts.

    New or changed files are read by ``workers`` threads (default: the CPU count, at most 4): the
    SHA-256 and a LibRaw decode, the costly parts, release the GIL; each holds one file at a time.
    ``allow_outside``: files a session.toml names (a flat field) may lie outside the session
    folder (absolute paths, ``..``, symlinks out), and capture files that are symbolic links out
    of the tree are read; by default both are refused (``error`` rows). ``progress``: a callback
    told of each file read or reused (:mod:`f2l.io.progress`)."""
    from concurrent.futures import ThreadPoolExecutor

    from f2l.io.tables import rows_to_table, write_table_atomic

    root, work = Path(root), Path(work)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: not a folder")
    work.mkdir(parents=True, exist_ok=True)
    table_path = work / TABLE_NAME
    previous = _previous(table_path)
    summary = ing.IngestSummary(root=str(root), table=str(table_path))
    # (path, relative path, stat, previous row or None when it must be read, why it is not opened)
    linked_out: list = []
    base = os.path.realpath(root)
    todo = [_scan_item(root, path, previous, allow_outside, base) for path in ing.scan(root, linked_out)]
    seen = Counter(item[1] for item in todo)
    for k, item in enumerate(todo):  # an escaped name that equals a real one: keep the key unique
        if item[4] is not None and seen[item[1]] > 1:
            todo[k] = (item[0], f"{item[1]} [unreadable name {k}]", *item[2:])

    def one(item) -> dict:
        path, rel, stat, old, why = item
        if why is not None:
            row = _unusable_row(path, rel, stat, why)
            row["_content_role"] = None
        elif old is not None:
            row = dict(old)
            row["_content_role"] = old["role"] if old["role_source"] == "detected" and old["role"] in CONTENT_ROLES else None
        else:
            row = _read_row(path, rel, ing.kind_of(path), stat)
            row["_content_role"] = None
        row["_file_error"] = row["sha256"] == ""  # reading the file failed: keep its message
        return row

    n_workers = max(1, min(4, os.cpu_count() or 1) if workers is None else int(workers))
    with ThreadPoolExecutor(max_workers=n_workers) as pool:
        bar = Progress(progress, "ingest", "file", len(todo))
        rows = []
        for row in pool.map(one, todo):  # in scan order
            rows.append(row)
            bar.advance()
    summary.reused = sum(item[3] is not None for item in todo)
    summary.read = len(todo) - summary.reused
    _derive(root, rows, session_gap_min, bracket_gap_s, detect_roles, summary, allow_outside)
    summary.warnings.extend(f"{st.shown_path(link)}: a symbolic link to a folder outside the capture tree "
                            f"(to {st.shown_path(target)}): not scanned (ingest never follows links to folders)"
                            for link, target in linked_out)
    for r in rows:
        r.pop("_file_error")
        r.pop("_content_role")
        r.pop("_view_problem", None)
        for k, v in r.items():  # parquet strings are UTF-8: a message may quote a path that is not
            if isinstance(v, str) and not st.is_utf8(v):
                r[k] = st.shown_path(v)
    summary.root, summary.table = st.shown_path(summary.root), st.shown_path(summary.table)
    summary.session_problems = [st.shown_path(x) for x in summary.session_problems]
    summary.warnings = [st.shown_path(x) for x in summary.warnings]
    rows.sort(key=lambda r: r["path"])
    write_table_atomic(rows_to_table(rows, "captures"), table_path, "captures")
    summary.files = len(rows)
    summary.by_status = dict(sorted(Counter(r["status"] for r in rows).items()))
    summary.by_role = dict(sorted(Counter(r["role"] for r in rows).items()))
    return summary


def _session_files(config: dict, folder: Path, root: Path, allow_outside: bool) -> dict[str, dict | str]:
    """Every file the session TOML names (``st.session_files``) by key path → {"file": path
    relative to the capture root (absolute where it lies outside and that is allowed), "sha256",
    "allow_outside" when outside, "real": its resolved path}, or why it is refused or unusable.
    Nothing is opened before it is known to be inside the session folder (or allowed) and a
    regular file."""
    out: dict[str, dict | str] = {}
    for where, name in st.session_files(config):
        try:
            path, outside = st.resolve_session_file(folder, name, allow_outside=allow_outside)
        except st.OutsideError as exc:
            out[where] = f"{exc}: refused (f2l ingest --allow-outside allows it)"
            continue
        why = st.regular_file(path)
        if why:
            out[where] = f"flat-field file {name!r} {why} (at {st.shown_path(path)})"
            continue
        try:
            sha = file_sha256(path)
        except OSError as exc:
            out[where] = f"flat-field file {name!r} cannot be read ({exc.strerror or exc})"
            continue
        if outside:
            info = {"file": os.path.abspath(path), "allow_outside": True}
        else:
            info = {"file": Path(os.path.relpath(os.path.normpath(path), root)).as_posix()}
        out[where] = dict(info, sha256=sha, real=os.path.realpath(path))
    return out


def _view_spec(view: dict, config: dict, shot: int | None, files: dict) -> tuple[ViewSpec, str]:
    """(spec, problem): the view the session TOML gives one file, parsed and validated once
    (:class:`~f2l.capture.view_spec.ViewSpec`), its flat-field file as recorded by
    :func:`_session_files` (a path relative to the capture root plus its SHA-256, so a changed
    file changes the merge's cache key). problem "<key>: why" when the view is invalid (then the
    spec is empty) or its flat-field file was refused or cannot be used."""
    try:
        spec = ViewSpec.from_dict(view)
    except ViewSpecError as exc:
        return ViewSpec(), f"{st.key_where(config, shot, exc.key)}: {exc} (the lens cannot place this view)"
    falloff = spec.lens.falloff
    if falloff is None or not falloff.file:
        return spec, ""
    where = st.key_where(config, shot, "falloff") + "/file"
    info = files.get(where)
    if not isinstance(info, dict):
        return spec, f"{where}: {info or 'not resolved'}"
    return spec.with_flat_field(info["file"], info["sha256"], info.get("allow_outside", False)), ""


def _lens_problem(spec: ViewSpec, row: dict, config: dict, shot: int | None) -> str:
    """"<key>: why" when the spec's lens cannot place a frame of the row's size (checked only
    for a frame of known size whose view describes a lens), else ""."""
    from f2l.capture.lens import LensError, lens_of

    if row["kind"] not in ("raw", "image") or not spec.lens.describes_geometry:
        return ""
    if not (row.get("width") and row.get("height")):
        return ""
    try:
        lens_of(spec.lens, int(row["width"]), int(row["height"]), row.get("focal_length_mm"))
    except LensError as exc:
        return f"{st.key_where(config, shot, exc.key)}: {exc} (the lens cannot place this view)"
    return ""


def _refuse(r: dict, root: Path, s: str, toml: str, summary: ing.IngestSummary, seen: dict) -> None:
    """Make a frame whose view cannot be used an ``error`` row and say so once per session and key."""
    problem = r["_view_problem"]
    r["status"], r["message"], r["bracket_id"] = "error", f"{st.shown_path(root / r['path'])}: {toml}: {problem}", None
    key = f"session {s}: {toml}: {problem}"
    if key not in seen:
        seen[key] = len(summary.warnings)
        summary.warnings.append(key)


def _derive(root: Path, rows: list[dict], session_gap_min: float, bracket_gap_s: float,
            detect_roles: bool, summary: ing.IngestSummary, allow_outside: bool = False) -> None:
    """Sessions, TOML views, roles, brackets and statuses, recomputed on every run; content
    detection runs only for files without a cached detected role."""
    loose = [r for r in rows if ing._session_of(Path(r["path"])) is None]
    for r in rows:
        r["session"] = ing._session_of(Path(r["path"])) or ""
    for k, group in enumerate(br.split_by_time(loose, session_gap_min * 60.0)):
        for r in group:
            r["session"] = f"{root.name or 'root'}-{k + 1:02d}"
    sessions = sorted({r["session"] for r in rows})
    summary.sessions = len(sessions)
    detector = ing.ContentRoles() if detect_roles else None
    for s in sessions:
        members = [r for r in rows if r["session"] == s]
        in_folder = (root / s).is_dir() and any(ing._session_of(Path(r["path"])) for r in members)
        is_loose = not any(ing._session_of(Path(r["path"])) for r in members)
        folder = root / s if in_folder else root
        config, problem = st.load_session_toml(folder) if (in_folder or is_loose) else ({}, "")
        toml = st.shown_path(folder / st.SESSION_TOML)
        if problem:
            summary.session_problems.append(f"session {s}: {problem} (session ingested without it)")
        rels = {id(r): Path(r["path"]).relative_to(s).as_posix() if in_folder else r["path"] for r in members}
        summary.warnings.extend(f"session {s}: {toml}: {w}"
                                for w in st.unmatched_globs(config, list(rels.values())))
        files = _session_files(config, folder, root, allow_outside)
        flat = {info["real"]: where for where, info in files.items() if isinstance(info, dict)}
        flat_rows = {}  # id(row) -> key path of a row that is a named flat field
        if flat:
            for r in members:
                where = flat.get(os.path.realpath(root / r["path"]))
                if where is not None:
                    flat_rows[id(r)] = where
        unreadable_flat = {flat[os.path.realpath(root / r["path"])]: r["message"]
                           for r in members if id(r) in flat_rows and r["_file_error"]}
        for r in members:
            rel_in = rels[id(r)]
            shot = st.matched_shot(config, rel_in)
            spec, view_problem = _view_spec(st.view_for(config, rel_in), config, shot, files)
            where = st.key_where(config, shot, "falloff") + "/file"
            if not view_problem and where in unreadable_flat and spec.lens.falloff and spec.lens.falloff.file:
                view_problem = f"{where}: the flat-field file is unreadable ({unreadable_flat[where]})"
            r["_view_problem"] = view_problem or _lens_problem(spec, r, config, shot)
            r["view_json"] = spec.to_json()
            r["session_problem"] = problem
            role, source = ing._folder_role(Path(r["path"])), "folder"
            if id(r) in flat_rows:  # a flat field is calibration data, never a probe or a frame
                role, source = "other", "toml"
            if role is None and spec.role is not None:
                role, source = spec.role, "toml"
            if role is None and r["kind"] == "hdr":
                role, source = "probe", "detected"
            if role is None:
                role, source = "other", "none"
            r["role"], r["role_source"], r["bracket_id"] = role, source, None
            if not r["_file_error"]:
                r["status"] = "ok"
                r["message"] = f"{problem} (session ingested without it)" if problem else ""
        seen: dict = {}
        for r in members:  # declared sky frames whose view cannot be used: not bracketed
            if r["_view_problem"] and r["role"] == "sky_bracket" and r["status"] == "ok":
                _refuse(r, root, s, toml, summary, seen)
        n_brackets = br.assign_brackets(members, bracket_gap_s)
        bad = {r["bracket_id"] for r in members if r["bracket_id"] and r["_view_problem"]}
        for r in members:  # detected brackets of such frames are dissolved
            if r["bracket_id"] in bad and r["_view_problem"]:
                _refuse(r, root, s, toml, summary, seen)
            elif r["bracket_id"] in bad:
                r["bracket_id"] = None
        summary.brackets += n_brackets - len(bad)
        summary.bracket_list.extend(br.bracket_summary(members))
        for r in members:  # content detection for what is still undecided
            if r["role_source"] != "none" or r["status"] != "ok":
                continue
            role = r["_content_role"]
            if role is None and detector is not None:
                try:
                    role = detector(root / r["path"], r["kind"])
                except Exception as exc:  # a preview that cannot be decoded: say so, go on
                    r["message"] = f"{root / r['path']}: role detection failed ({exc})"
            if role is not None:
                r["role"], r["role_source"] = role, "detected"
