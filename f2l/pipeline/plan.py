"""What each session needs, from the rows of ``WORK/captures.parquet``.

Per session (sorted by name; files by relative path):

- ``faces``: ok rows with role ``face``; ``charts``: ok rows with role ``chart``;
  ``given_probes``: ok rows with role ``probe`` and kind ``hdr``; ``brackets``: ``bracket_id`` →
  its ok frames.
- Stages a session does not need are left out, each with its reason in ``skipped``: no face
  photos → no merge, sphere or calibration (nothing would use them); a given probe → no merge or
  sphere (the first given probe, by path, is the session's probe; other given probes and the
  brackets are listed as left out); no chart → no calibration (identity correction, a warning).
- Rows that are not used at all go to ``left_out`` with the reason: ingest status ``error`` or
  ``skipped`` (the ingest message), role ``other``.

Messages never hold absolute paths: :func:`relative_message` strips the capture root.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from f2l.capture.view_spec import ViewSpec, ViewSpecError


def relative_message(message: str, root: str | os.PathLike) -> str:
    """``message`` with the capture root removed from the paths in it: the absolute forms
    anywhere (as written and with symlinks resolved), the form as given only at the start."""
    out = message or ""
    root = Path(root)
    for prefix in sorted({os.path.abspath(root), str(root.resolve())}, key=len, reverse=True):
        out = out.replace(prefix.rstrip("/") + "/", "")
    given = str(root).rstrip("/") + "/"
    if not root.is_absolute() and out.startswith(given):
        out = out[len(given):]
    return out


@dataclass
class SessionPlan:
    """One session's inputs (``captures`` rows) and the stages it skips (``{stage: reason}``)."""

    name: str
    faces: list = field(default_factory=list)
    charts: list = field(default_factory=list)
    given_probes: list = field(default_factory=list)
    brackets: dict = field(default_factory=dict)
    skipped: dict = field(default_factory=dict)

    @property
    def given_probe(self) -> dict | None:
        return self.given_probes[0] if self.given_probes else None

    def _probe_azimuth(self) -> tuple[float | None, str | None]:
        """(the session TOML's ``probe_azimuth_deg`` from the first of its rows by path that gives
        it, or None; why a row's value cannot be used, or None)."""
        rows = self.faces + self.charts + self.given_probes + [
            f for frames in self.brackets.values() for f in frames]
        for row in sorted(rows, key=lambda r: r["path"]):
            try:
                spec = ViewSpec.from_json(row["view_json"])
            except ViewSpecError as exc:
                if exc.key == "probe_azimuth_deg":
                    return None, f"session.toml: {exc}"
                continue
            if spec.probe_azimuth_deg is not None:
                return float(spec.probe_azimuth_deg), None
        return None, None

    @property
    def probe_azimuth_deg(self) -> float | None:
        """The session TOML's ``probe_azimuth_deg`` (from any of its rows), None when not given
        or not a finite angle (:attr:`probe_azimuth_problem` says which)."""
        return self._probe_azimuth()[0]

    @property
    def probe_azimuth_problem(self) -> str | None:
        """Why the session's ``probe_azimuth_deg`` cannot turn its probe (given, but not a finite
        angle), or None."""
        return self._probe_azimuth()[1]


def _left(row: dict, stage: str, status: str, reason: str, root) -> dict:
    return {"path": row["path"], "stage": stage, "status": status,
            "reason": relative_message(reason, root)}


def plan_sessions(rows: list[dict], root: str | os.PathLike, *, with_probes: bool,
                  with_calibration: bool) -> tuple[list[SessionPlan], list[dict]]:
    """(sessions, left_out) from ``captures`` rows (module docstring). ``with_probes`` /
    ``with_calibration``: whether the pipeline has the merge+sphere / calibrate stages."""
    sessions: dict[str, SessionPlan] = {}
    left_out: list[dict] = []
    for row in sorted(rows, key=lambda r: r["path"]):
        plan = sessions.setdefault(row["session"], SessionPlan(row["session"]))
        if row["status"] != "ok":
            left_out.append(_left(row, "ingest", row["status"], row["message"], root))
        elif row["role"] == "face":
            plan.faces.append(row)
        elif row["role"] == "chart":
            plan.charts.append(row)
        elif row["role"] == "probe" and row["kind"] == "hdr":
            plan.given_probes.append(row)
        elif row["role"] == "sky_bracket" and row["bracket_id"]:
            plan.brackets.setdefault(row["bracket_id"], []).append(row)
        else:
            left_out.append(_left(row, "ingest", "unused",
                                  f"role {row['role']} ({row['kind']}): not used by the pipeline",
                                  root))
    for plan in sessions.values():
        _decide(plan, left_out, root, with_probes, with_calibration)
    left_out.sort(key=lambda r: (r["path"], r["stage"]))
    return [sessions[k] for k in sorted(sessions)], left_out


def _decide(plan: SessionPlan, left_out: list, root, with_probes: bool,
            with_calibration: bool) -> None:
    bracket_rows = [f for bid in sorted(plan.brackets) for f in plan.brackets[bid]]
    if not plan.faces:
        reason = "no face photos in the session: nothing would use it"
        plan.skipped.update({"merge": reason, "sphere": reason, "calibrate": reason})
        for row in bracket_rows + plan.charts + plan.given_probes:
            left_out.append(_left(row, "plan", "unused", reason, root))
        plan.brackets, plan.charts, plan.given_probes = {}, [], []
        return
    if plan.given_probe is not None:
        given = plan.given_probe["path"]
        reason = f"the session has a given probe ({given})"
        for row in bracket_rows:
            left_out.append(_left(row, "merge", "unused", reason, root))
        for row in plan.given_probes[1:]:
            left_out.append(_left(row, "sphere", "unused", f"{reason}; one probe per session",
                                  root))
        plan.given_probes = plan.given_probes[:1]
        plan.brackets = {}
        plan.skipped.update({"merge": reason, "sphere": reason})
    elif not with_probes:
        reason = "the pipeline has no merge/sphere stages"
        for row in bracket_rows:
            left_out.append(_left(row, "merge", "unused", reason, root))
        plan.brackets = {}
        plan.skipped.update({"merge": reason, "sphere": reason})
    elif not plan.brackets:
        reason = "no sky brackets and no given probe: faces have no ground-truth probe"
        plan.skipped.update({"merge": reason, "sphere": reason})
    if not with_calibration:
        for row in plan.charts:
            left_out.append(_left(row, "calibrate", "unused",
                                  "the pipeline has no calibrate stage", root))
        plan.charts = []
        plan.skipped["calibrate"] = "the pipeline has no calibrate stage: identity correction"
    elif not plan.charts:
        plan.skipped["calibrate"] = "no chart photo in the session: identity correction"
