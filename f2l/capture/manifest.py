"""The incremental ingest run: scan → (reuse or read) rows → sessions, roles, brackets →
``WORK/captures.parquet`` (atomic). See :mod:`f2l.capture.ingest` for what each column means."""

from __future__ import annotations

import json
import os
from collections import Counter
from pathlib import Path

from f2l.capture import ingest as ing
from f2l.io.hashing import file_sha256

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


def _read_row(path: Path, rel: str, kind: str, stat: os.stat_result) -> dict:
    row = {"path": rel, "sha256": "", "size_bytes": int(stat.st_size),
           "mtime_ns": int(stat.st_mtime_ns), "kind": kind, "session": "", "role": "other",
           "role_source": "none", "bracket_id": None, "status": "ok", "message": "",
           "view_json": "{}", "session_problem": "", "ingest_version": ing.INGEST_VERSION, **ing._empty_meta()}
    try:
        row.update(ing.read_file_meta(path, kind))
        row["sha256"] = file_sha256(path)
    except Exception as exc:  # bad input never stops the ingest: the row says why
        msg = str(exc)
        row.update(status="error", message=msg if msg.startswith(str(path)) else f"{path}: {msg}")
    return row


CONTENT_ROLES = ("face", "chart", "other")


def _unchanged(old: dict | None, stat: os.stat_result) -> bool:
    return (old is not None and old["size_bytes"] == stat.st_size
            and old["mtime_ns"] == stat.st_mtime_ns
            and old["ingest_version"] == ing.INGEST_VERSION)


def run_ingest(root: str | os.PathLike, work: str | os.PathLike, *,
               session_gap_min: float = 30.0, bracket_gap_s: float = 15.0,
               detect_roles: bool = True, progress: bool = False, workers: int | None = None) -> ing.IngestSummary:
    """Ingest the tree under ``root`` into ``work/captures.parquet``; returns counts.

    New or changed files are read by ``workers`` threads (default: the CPU count, at most 4): the
    SHA-256 and a LibRaw decode, the costly parts, release the GIL; each holds one file at a time."""
    from concurrent.futures import ThreadPoolExecutor

    from f2l.io.tables import rows_to_table, write_table_atomic

    root, work = Path(root), Path(work)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: not a folder")
    work.mkdir(parents=True, exist_ok=True)
    table_path = work / TABLE_NAME
    previous = _previous(table_path)
    summary = ing.IngestSummary(root=str(root), table=str(table_path))
    todo = []  # (path, relative path, stat, previous row or None when it must be read)
    for path in ing.scan(root):
        rel, stat = path.relative_to(root).as_posix(), path.stat()
        old = previous.get(rel)
        todo.append((path, rel, stat, old if _unchanged(old, stat) else None))

    def one(item) -> dict:
        path, rel, stat, old = item
        if old is not None:
            row = dict(old)
            row["_content_role"] = old["role"] if old["role_source"] == "detected" and old["role"] in CONTENT_ROLES else None
        else:
            row = _read_row(path, rel, ing.kind_of(path), stat)
            row["_content_role"] = None
        row["_file_error"] = row["sha256"] == ""  # reading the file failed: keep its message
        return row

    n_workers = max(1, min(4, os.cpu_count() or 1) if workers is None else int(workers))
    with ThreadPoolExecutor(max_workers=n_workers) as pool:
        results = pool.map(one, todo)  # in scan order
        if progress:
            from tqdm import tqdm

            results = tqdm(results, total=len(todo), desc="ingest", unit="file")
        rows = list(results)
    summary.reused = sum(item[3] is not None for item in todo)
    summary.read = len(todo) - summary.reused
    _derive(root, rows, session_gap_min, bracket_gap_s, detect_roles, summary)
    for r in rows:
        r.pop("_file_error")
        r.pop("_content_role")
    rows.sort(key=lambda r: r["path"])
    write_table_atomic(rows_to_table(rows, "captures"), table_path, "captures")
    summary.files = len(rows)
    summary.by_status = dict(sorted(Counter(r["status"] for r in rows).items()))
    summary.by_role = dict(sorted(Counter(r["role"] for r in rows).items()))
    return summary


def _with_files(view: dict, root: Path, session_dir: str) -> dict:
    """A flat-field file named in the view, as a path relative to the capture root plus its
    SHA-256 (so a changed file changes the merge's cache key); a missing file is left to the merge
    to report."""
    falloff = view.get("falloff")
    if not (isinstance(falloff, dict) and falloff.get("file")):
        return view
    rel = (Path(session_dir) / falloff["file"]).as_posix()
    path = root / rel
    view = dict(view, falloff=dict(falloff, file=rel, sha256=file_sha256(path) if path.is_file() else ""))
    return view


def _derive(root: Path, rows: list[dict], session_gap_min: float, bracket_gap_s: float,
            detect_roles: bool, summary: ing.IngestSummary) -> None:
    """Sessions, TOML views, roles, brackets and statuses, recomputed on every run; content
    detection runs only for files without a cached detected role."""
    loose = [r for r in rows if ing._session_of(Path(r["path"])) is None]
    for r in rows:
        r["session"] = ing._session_of(Path(r["path"])) or ""
    for k, group in enumerate(ing.split_by_time(loose, session_gap_min * 60.0)):
        for r in group:
            r["session"] = f"{root.name or 'root'}-{k + 1:02d}"
    sessions = sorted({r["session"] for r in rows})
    summary.sessions = len(sessions)
    detector = ing.ContentRoles() if detect_roles else None
    for s in sessions:
        members = [r for r in rows if r["session"] == s]
        in_folder = (root / s).is_dir() and any(ing._session_of(Path(r["path"])) for r in members)
        config, problem = ing.load_session_toml(root / s if in_folder else root)
        if problem:
            summary.session_problems.append(f"session {s}: {problem} (session ingested without it)")
        for r in members:
            rel_in = Path(r["path"]).relative_to(s).as_posix() if in_folder else r["path"]
            view = _with_files(ing.view_for(config, rel_in), root, s if in_folder else "")
            r["view_json"] = json.dumps(view, sort_keys=True)
            r["session_problem"] = problem
            role, source = ing._folder_role(Path(r["path"])), "folder"
            if role is None and "role" in view:
                role, source = view["role"], "toml"
            if role is None and r["kind"] == "hdr":
                role, source = "probe", "detected"
            if role is None:
                role, source = "other", "none"
            r["role"], r["role_source"], r["bracket_id"] = role, source, None
            if not r["_file_error"]:
                r["status"] = "ok"
                r["message"] = f"{problem} (session ingested without it)" if problem else ""
        summary.brackets += ing.assign_brackets(members, bracket_gap_s)
        summary.bracket_list.extend(ing.bracket_summary(members))
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
