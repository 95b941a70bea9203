"""The stages of one build, in order (called by :func:`f2l.pipeline.build.build_dataset` under
its lock). Each step fills ``summary`` (counts per stage, seconds per stage) and collects what
the dataset card says: per-session facts, left-out inputs and warnings (paths relative to the
capture root)."""

from __future__ import annotations

import time
from pathlib import Path

from f2l.capture.view_spec import ViewSpec, ViewSpecError
from f2l.io.progress import Progress, ProgressCallback
from f2l.pipeline import assemble, card, faces, probes
from f2l.pipeline.plan import plan_sessions, relative_message
from f2l.pipeline.publish import CARD_NAME, publish, up_to_date


class _Clock:
    """Seconds per step into ``summary.stage_seconds``; one line per step to ``say``."""

    def __init__(self, summary, say):
        self.summary, self.say, self.t = summary, say, time.perf_counter()

    def lap(self, step: str, line: str) -> None:
        now = time.perf_counter()
        self.summary.stage_seconds[step] = round(now - self.t, 3)
        self.t = now
        self.say(f"{step}: {line}")

    def counts(self, *stages: str) -> str:
        return "; ".join(f"{s} {self.summary.stages[s]['computed']} computed, "
                         f"{self.summary.stages[s]['reused']} reused" for s in stages)


def _ingest(spec, root: Path, work: Path, summary) -> list[dict]:
    import pyarrow.parquet as pq

    from f2l.capture.manifest import TABLE_NAME, run_ingest

    p = spec.params("ingest")
    result = run_ingest(root, work, session_gap_min=float(p["session_gap_min"]),
                        bracket_gap_s=float(p["bracket_gap_s"]),
                        detect_roles=bool(p["detect_roles"]),
                        allow_outside=bool(p.get("allow_outside", False)))
    summary.ingest = {"files": result.files, "read": result.read, "reused": result.reused,
                      "sessions": result.sessions, "brackets": result.brackets}
    return pq.read_table(work / TABLE_NAME).to_pylist()


def _session_probe(cache, root, plan, spec, counts, timings, left_out, warnings):
    """(probe entry or None, sky camera or None for a given probe, brackets merged) of one
    session. A probe that failed (an ``error`` row: unreadable, black, uncovered, NaN) or that
    could not be computed at all is left out with its reason and is never ground truth; one
    session's failure never stops the build."""
    try:
        return _session_probe_or_raise(cache, root, plan, spec, counts, timings, left_out, warnings)
    except Exception as exc:  # noqa: BLE001 - recorded for this session; the other sessions go on
        what = plan.given_probe["path"] if plan.given_probe is not None else plan.name
        reason = relative_message(f"{type(exc).__name__}: {exc}", root)
        left_out.append({"path": what, "stage": "sphere", "status": "error",
                         "reason": f"session {plan.name}: probe not computed: {reason}"})
        warnings.append(f"session {plan.name}: probe failed ({what}): {reason}: its faces have no "
                        f"ground-truth probe")
        return None, None, 0


def _session_probe_or_raise(cache, root, plan, spec, counts, timings, left_out, warnings):
    grid_hw = (spec.grid_height, spec.grid_width)
    if plan.given_probe is not None:
        probe = probes.given_probe(cache, root, plan, grid_hw, counts["sphere"])
        sky_camera, n_ok, what = None, 0, plan.given_probe["path"]
    elif plan.brackets:
        merged = probes.merge_session(cache, root, plan, spec.params("merge"), counts["merge"],
                                      timings)
        failed = []
        for m in merged:
            if m["row"]["status"] != "ok":
                failed.append(f"{m['row']['name']} {m['row']['status']}: {m['row']['message']}")
                for frame in sorted(plan.brackets[m["row"]["name"]], key=lambda f: f["path"]):
                    left_out.append({"path": frame["path"], "stage": "merge",
                                     "status": m["row"]["status"], "reason": m["row"]["message"]})
        n_ok = sum(m["row"]["status"] == "ok" for m in merged)
        probe = probes.sphere_session(cache, plan, merged, grid_hw, counts["sphere"], timings,
                                      bool(spec.params("sphere").get("restore_sun", False)))
        first = sorted(plan.brackets[sorted(plan.brackets)[0]], key=lambda f: f["path"])[0]
        sky_camera = first["camera"] or ""
        what = "assembled from " + ", ".join(sorted(plan.brackets))
        if probe is None:
            warnings.append(f"session {plan.name}: no bracket could be placed on the sphere ("
                            + "; ".join(failed) + "): its faces have no ground-truth probe")
    else:
        return None, None, 0
    if probe is not None and probe["row"]["status"] != "ok":
        row = probe["row"]
        left_out.append({"path": row["name"], "stage": "sphere", "status": row["status"],
                         "reason": row["message"]})
        warnings.append(f"session {plan.name}: probe failed ({what}): {row['message'] or row['status']}: "
                        f"its faces have no ground-truth probe")
        probe = None
    return probe, sky_camera, n_ok


def _photo_left_out(fit: dict) -> list[dict]:
    if fit["status"] != "ok":
        return [{"path": fit["path"], "stage": "fit-faces", "status": fit["status"],
                 "reason": fit["message"]}]
    return [{"path": fit["path"], "stage": "fit-faces", "status": r["reason"],
             "reason": r["message"]} for r in fit["rejected"]]


def run_stages(spec, root: Path, work: Path, out: Path, cache, summary, landmarker_path,
               say, progress: ProgressCallback | None = None, executor: dict | None = None) -> None:
    """Ingest → plan → probes, charts → faces → pairing, shards → card → publish. ``executor``:
    ``{"name": "ray", "address": ..., "workers": N}`` makes the per-item entries on Ray first
    (:mod:`f2l.pipeline.ray_build`); the local pass then only reads them. ``progress``: a callback
    told of each face photo fitted (:mod:`f2l.io.progress`)."""
    clock = _Clock(summary, say)
    rows = _ingest(spec, root, work, summary)
    clock.lap("ingest", f"{summary.ingest['read']} read, {summary.ingest['reused']} unchanged")
    sessions, left_out = plan_sessions(rows, root, with_probes=spec.has("merge"),
                                       with_calibration=spec.has("calibrate"))
    counts = {s: {"computed": 0, "reused": 0} for s in
              ("merge", "sphere", "calibrate", "fit-faces", "gt-probe", "shards")}
    summary.stages = counts
    timings: dict = {}
    on_ray = {}
    if executor and executor.get("name") == "ray":
        from f2l.pipeline.ray_build import prewarm

        on_ray = prewarm(spec, root, work, sessions, landmarker_path, token=executor["token"],
                         address=executor.get("address"), workers=int(executor.get("workers", 2)),
                         progress=progress)
        failed = on_ray.pop("failed", 0)  # tasks that raised: computed (and recorded) below
        summary.on_executor = dict(on_ray)
        clock.lap("ray", ", ".join(f"{k} {v}" for k, v in on_ray.items()) + " entries made on Ray"
                  + (f"; {failed} task(s) failed, computed again here" if failed else ""))
    problems = sorted({(r["session"], r["session_problem"]) for r in rows if r.get("session_problem")})
    warnings: list[str] = [f"session {session}: session.toml not used: {relative_message(problem, root)}"
                           for session, problem in problems]
    state = _probes_and_charts(cache, root, spec, sessions, counts, timings, left_out, warnings)
    clock.lap("probes+calibrate", clock.counts("merge", "sphere", "calibrate"))
    fits = _fit_all(cache, root, spec, sessions, counts, timings, landmarker_path, progress)
    clock.lap("fit-faces", clock.counts("fit-faces") + " (transport inside)")
    photos, session_cards = _pair(cache, spec, sessions, state, fits, counts, left_out, warnings)
    chunks = assemble.shard_chunks(photos, spec.params("shards")["photos_per_shard"])
    keep_exposure = bool(spec.params("calibrate").get("keep_exposure", False))
    shards = [assemble.write_shard(cache, chunk, keep_exposure, counts["shards"], timings)
              for chunk in chunks]
    files = _output_files(spec, shards, photos, state)
    clock.lap("shards", clock.counts("gt-probe", "shards"))
    doc = card.make_card(
        pipeline_json=spec.to_json(), version_info=card.versions(), inputs=card.input_list(rows),
        sessions=session_cards,
        shards=[{"file": f"part-{i:05d}.parquet", "records": s["records"], "key": s["key"]}
                for i, s in enumerate(shards)],
        counts={"files": len(rows), "sessions": len(sessions),
                "sessions_with_probe": sum(st["gt"] is not None for st in state.values()),
                "brackets_merged": sum(st["brackets_ok"] for st in state.values()),
                "charts": sum(len(st["charts"]) for st in state.values()),
                "face_photos": sum(len(f) for f in fits.values()),
                "face_photos_used": len(photos), "records": sum(s["records"] for s in shards),
                "records_with_gt_probe": sum(len(p["face_ids"]) for p in photos
                                             if p["gt"] is not None),
                "shards": len(shards), "left_out": len(left_out)},
        left_out=left_out, warnings=warnings, files=files)
    for stage, made in on_ray.items():  # made on Ray: computed, not reused, by this build
        counts[stage]["computed"] += made
        counts[stage]["reused"] -= made
    text = card.card_text(doc)
    summary.counts, summary.warnings = doc["counts"], doc["warnings"]
    summary.failed = [r for r in doc["left_out"] if r["status"] == "error"]
    if up_to_date(work, out, files, text):
        summary.publish = {"written": 0, "kept": len(files), "removed": 0}
        summary.nothing_to_do = not any(c["computed"] for c in counts.values())
    else:
        summary.publish = publish(work, out, files, text)
    clock.lap("publish", f"{summary.publish['written']} written, {summary.publish['kept']} "
                         f"kept, {summary.publish['removed']} removed -> {out / CARD_NAME}")
    summary.stage_seconds["items"] = timings


def _probes_and_charts(cache, root, spec, sessions, counts, timings, left_out, warnings) -> dict:
    """{session: {"probe", "sky_camera", "charts", "brackets_ok"}}."""
    state = {}
    for plan in sessions:
        probe, sky_camera, n_ok = _session_probe(cache, root, plan, spec, counts, timings,
                                                 left_out, warnings)
        charts = [faces.calibrate_chart(cache, root, row, spec.params("calibrate"),
                                        counts["calibrate"], timings) for row in plan.charts]
        for c in charts:
            if c["status"] not in assemble.USABLE_CHART:
                left_out.append({"path": c["path"], "stage": "calibrate", "status": c["status"],
                                 "reason": c["reason"]})
        state[plan.name] = {"probe": probe, "sky_camera": sky_camera, "charts": charts,
                            "brackets_ok": n_ok}
    return state


def _fit_all(cache, root, spec, sessions, counts, timings, landmarker_path, progress) -> dict:
    """{session: [fit-faces result per face photo, by path]}; each photo fitted is told to ``progress``."""
    fitter = faces.FaceFitter(cache, root, spec.params("fit-faces"), spec.params("transport"),
                              (spec.grid_height, spec.grid_width), landmarker_path)
    bar = Progress(progress, "fit-faces", "photo", sum(len(p.faces) for p in sessions))
    fits = {}
    for plan in sessions:
        fits[plan.name] = []
        for row in plan.faces:
            fit = fitter(row, counts["fit-faces"], timings)
            yaw = _camera_yaw(row)
            if yaw is not None:  # the face camera's heading in the session ([[shots]] yaw_deg): joint estimates
                fit["camera_yaw_deg"] = yaw
            fits[plan.name].append(fit)
            bar.advance(1)
    return fits


def _pair(cache, spec, sessions, state, fits, counts, left_out, warnings):
    """Photos with records, paired with their correction and ground-truth probe; and the
    card's per-session facts."""
    calib = spec.params("calibrate")
    keep_exposure = bool(calib.get("keep_exposure", False))
    photos, cards, seen = [], [], {}
    for plan in sessions:
        st = state[plan.name]
        st["gt"] = None
        if st["probe"] is not None and plan.probe_azimuth_problem:
            left_out.append({"path": st["probe"]["row"]["name"], "stage": "gt-probe", "status": "error",
                             "reason": f"session {plan.name}: {plan.probe_azimuth_problem}"})
            warnings.append(f"session {plan.name}: probe failed: {plan.probe_azimuth_problem}: the "
                            f"probe cannot be turned into the face camera's frame: its faces have no "
                            f"ground-truth probe")
            st["probe"] = None
        if st["probe"] is not None:
            if st["sky_camera"] is None:
                chart, note = None, "a given probe is used as it is (its colour space is its own)"
            elif not calib.get("correct_probe", False):
                chart, note = None, "correct_probe = false in the pipeline: the probe is kept as merged"
            else:
                chart, note = assemble.pick_correction(st["charts"], st["sky_camera"])
            st["gt"] = assemble.gt_probe(cache, plan.name, st["probe"], chart, note,
                                         plan.probe_azimuth_deg, counts["gt-probe"])
            if st["gt"].get("problem"):
                reason = f"session {plan.name}: ground-truth probe refused: {st['gt']['problem']}"
                left_out.append({"path": st["probe"]["row"]["name"], "stage": "gt-probe",
                                 "status": "error", "reason": reason})
                warnings.append(f"{reason} (after {st['gt']['applied']['colour']['method']} colour "
                                f"correction): its faces have no ground-truth probe")
                st["gt"] = None
            if plan.probe_azimuth_deg is None:
                warnings.append(f"session {plan.name}: session.toml has no probe_azimuth_deg: "
                                f"the probe is in its tripod frame, not the face camera's")
        elif plan.faces:
            warnings.append(f"session {plan.name}: no probe: its faces have no ground truth")
        face_colour, records = {}, 0
        for fit in fits[plan.name]:
            left_out.extend(_photo_left_out(fit))
            if fit["status"] != "ok":
                continue
            dup = [fid for fid in fit["face_ids"] if fid in seen]
            if dup:
                left_out.append({"path": fit["path"], "stage": "shards", "status": "duplicate",
                                 "reason": f"same bytes and file name as {seen[dup[0]]}"})
                continue
            seen.update({fid: fit["path"] for fid in fit["face_ids"]})
            chart, note = assemble.pick_correction(st["charts"], fit["camera"])
            colour = assemble.colour_description(chart, note, keep_exposure)
            face_colour[fit["camera"]] = colour
            if chart is None:
                warnings.append(f"session {plan.name}, camera {fit['camera'] or 'unknown'}: "
                                f"{note}")
            photos.append({**fit, "session": plan.name, "chart": chart, "colour": colour,
                           "gt": st["gt"]})
            records += len(fit["face_ids"])
        probe_card = None
        if st["gt"] is not None:
            row = st["probe"]["row"]
            probe_card = {"source": row["kind"], "status": row["status"],
                          "file": f"probes/{assemble.safe_name(plan.name)}.exr",
                          "applied": st["gt"]["applied"], "coverage_fraction":
                          row.get("coverage_fraction"), "sun_elevation_deg":
                          row.get("sun_elevation_deg"), "sun_azimuth_deg_tripod":
                          row.get("sun_azimuth_deg"), "message": row["message"]}
        cards.append({"name": plan.name, "probe": probe_card, "face_colour": face_colour,
                      "face_photos": len(plan.faces), "records": records,
                      "skipped": dict(sorted(plan.skipped.items()))})
    photos.sort(key=lambda p: p["path"])
    return photos, cards


def _output_files(spec, shards, photos, state) -> dict:
    """{relative path in OUT: (source file, key)} of everything but the card."""
    files = {}
    for i, s in enumerate(shards):
        files[f"part-{i:05d}.parquet"] = (str(Path(s["entry"]) / "part-00000.parquet"), s["key"])
    overlays = bool(spec.params("fit-faces")["overlays"])
    for p in photos:
        for fid in p["face_ids"]:
            files[f"photos/{fid}.png"] = (str(Path(p["entry"]) / "photos" / f"{fid}.png"), p["key"])
            if overlays:
                files[f"overlays/{fid}.png"] = (str(Path(p["entry"]) / "overlays" / f"{fid}.png"),
                                                p["key"])
    used = {p["session"] for p in photos}
    for name, st in state.items():
        if st["gt"] is not None and name in used:
            files[f"probes/{assemble.safe_name(name)}.exr"] = (
                str(Path(st["gt"]["entry"]) / "probe.exr"), st["gt"]["key"])
    return files


def _camera_yaw(row: dict) -> float | None:
    """The face photo's camera heading from its session.toml view (``[[shots]]`` ``yaw_deg``), or None."""
    try:
        yaw = ViewSpec.from_json(row.get("view_json")).yaw_deg
    except ViewSpecError:
        return None
    return None if yaw is None else float(yaw)
