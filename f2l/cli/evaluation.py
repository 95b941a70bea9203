"""CLI layer of the independent evaluation renders (registered by :mod:`f2l.cli.app`):
``render-faces``, ``render-skies``, ``twin-geometry``, ``eval-real``, ``eval-real-geometry``,
``eval-real-search``, ``eval-real-ablations``, ``framings``, and the joint estimate's ``groups``,
``shade`` and ``sessions``."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from f2l.cli.common import JsonOut, fail, require_render_dirs
from f2l.cli.progress import progress_bars


def render_faces_cmd(
    out: Path = typer.Option(..., "--out", help="Output folder (photos/, png/, probes/, truth/, meta/)."),
    n: int = typer.Option(8, "--n", help="Number of cases."),
    seed: int = typer.Option(0, help="Random seed: case i of a seed is the same person, pose, camera and sky in every variant."),
    start: int = typer.Option(0, help="First case index (render a set in parts)."),
    image_px: Optional[int] = typer.Option(None, help="Photo size in pixels (square; default 384), or with --sequence the frame's long side (16:9; default 1280)."),
    spp: Optional[int] = typer.Option(None, help="Path-tracing samples per pixel (default 64; --sequence: 4 on the head, half that on the torso, denoised)."),
    max_depth: int = typer.Option(6, help="Path length: 6 includes interreflection; 2 is direct light only."),
    specular: bool = typer.Option(True, "--specular/--no-specular", help="Skin with a specular lobe (principled BSDF) or Lambertian."),
    head: str = typer.Option("anny", help="anny (random Anny adults) or canonical (MediaPipe's canonical face, closed: an ablation)."),
    clipping: bool = typer.Option(True, "--clipping/--no-clipping", help="Expose so the brightest few % of the face clip, or keep the face below 0.9."),
    sunsky_fraction: float = typer.Option(0.5, help="Fraction of cases under a Hosek-Wilkie sky (the rest: real HDR maps)."),
    maps: str = typer.Option("eval", help="Which real maps: eval (the seven of `make eval-real`) or held-out (city, sunrise, sunset: no default was chosen on them)."),
    framing: str = typer.Option("portrait", help="portrait (one head, 35-55% of a square frame), half (one person, head 12-25% of a 3:2 frame's long side), full (4-10%) or group (2-5 people, 5-14% each, one light); wider framings use --image-px as the long side (1280 suggested)."),
    shade_one: bool = typer.Option(False, "--shade-one", help="--framing group: under a clear sky a dark board puts one person's face in its shadow (meta: shaded_person)."),
    session_size: int = typer.Option(1, "--session-size", help="--framing portrait: sessions of K photos (cases jK..jK+K-1) under the first one's light, each with its own person and a camera turned within ±90° (meta: session, camera_yaw_deg); 1: off."),
    sequence: bool = typer.Option(False, "--sequence", help="Video clips instead of photos: one person turning (±45° yaw) and nodding under one light, a static camera, noise and mp4v compression (clips/, truth/, probes/, clips.json; f2l.render.sequence)."),
    clip_kind: str = typer.Option("mixed", "--clip-kind", help="--sequence: static (one light), cloud (the sun drops to 10-20% halfway), cut (another shot halfway) or mixed (clip i cycles them)."),
    frames: int = typer.Option(48, "--frames", help="--sequence: frames per clip."),
    fps: float = typer.Option(24.0, "--fps", help="--sequence: frames per second."),
    json_out: JsonOut = False,
) -> None:
    """Path-trace photos of heads f2l did not model (Mitsuba 3, Anny) under real HDR maps and physical skies, framed as portraits, half or full shots, or groups; or, with --sequence, video clips of a head turning and nodding."""
    from f2l.render import RenderExtraMissing
    from f2l.render.dataset import RenderOptions, render_faces
    from f2l.render.heads import require_anny
    from f2l.render.scene import mitsuba

    try:
        mitsuba()
        require_anny()
    except RenderExtraMissing as exc:
        fail(str(exc))
    if image_px is None:
        image_px = 1280 if sequence else 384
    if spp is None:
        spp = 4 if sequence else 64
    try:
        options = RenderOptions(image_px=image_px, spp=spp, max_depth=max_depth, specular=specular, head=head,
                                clipping=clipping, sunsky_fraction=sunsky_fraction, maps=maps, shade_one=shade_one)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from exc
    if sequence:
        _render_sequence(out, n, seed, start, options, clip_kind, frames, fps, json_out,
                         other=framing != "portrait" or shade_one or session_size != 1 or head != "anny")
        return
    from f2l.render.framing import FRAMINGS, render_framed

    if framing not in FRAMINGS:
        raise typer.BadParameter(f"must be one of {', '.join(FRAMINGS)}", param_hint="--framing")
    if shade_one and framing != "group":
        raise typer.BadParameter("only with --framing group", param_hint="--shade-one")
    if session_size < 1 or (session_size > 1 and framing != "portrait"):
        raise typer.BadParameter("at least 1, and above 1 only with --framing portrait", param_hint="--session-size")
    with progress_bars(not json_out) as progress:
        if framing == "portrait":
            summary = render_faces(out, n, seed, options, start=start, progress=progress, session_size=session_size)
        else:
            summary = render_framed(out, framing, n, seed, options, start=start, progress=progress)
    typer.echo(json.dumps(summary, indent=None if json_out else 2))
    if summary["cases"] and len(summary["errors"]) == summary["cases"]:
        raise typer.Exit(code=1)


def _render_sequence(out: Path, n: int, seed: int, start: int, options, clip_kind: str, frames: int, fps: float,
                     json_out: bool, other: bool) -> None:
    """``render-faces --sequence``: the clips of f2l.render.sequence, its index printed."""
    from f2l.render.sequence import SequenceOptions, render_clips

    if other:
        raise typer.BadParameter("--sequence renders one Anny person: no --framing, --shade-one, --session-size "
                                 "or --head canonical", param_hint="--sequence")
    try:
        sequence = SequenceOptions(frames=frames, fps=fps, clip_kind=clip_kind)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--clip-kind/--frames/--fps") from exc
    with progress_bars(not json_out) as progress:
        summary = render_clips(out, n, seed, options, sequence, start=start, progress=progress)
    typer.echo(json.dumps(summary, indent=None if json_out else 2))
    if summary["cases"] and len(summary["errors"]) == summary["cases"]:
        raise typer.Exit(code=1)


def render_skies_cmd(
    out: Path = typer.Option(..., "--out", help="Output folder for the sky EXRs (+ JSON side files)."),
    n: int = typer.Option(100, "--n", help="Number of skies."),
    seed: int = typer.Option(0, help="Seed (sky i of a seed is the same whatever --n is)."),
    json_out: JsonOut = False,
) -> None:
    """Write Hosek-Wilkie clear skies (Mitsuba 3) as 64x128 probes: a physically based corpus for `f2l prior build`."""
    from f2l.render import RenderExtraMissing
    from f2l.render.scene import mitsuba
    from f2l.render.skies import write_hosek_wilkie_corpus

    try:
        mitsuba()
    except RenderExtraMissing as exc:
        fail(str(exc))
    paths = write_hosek_wilkie_corpus(out, n, seed=seed)
    typer.echo(json.dumps({"written": len(paths), "out": str(out)}))


def twin_geometry_cmd(
    fitted: Path = typer.Argument(..., help="Shards written by `f2l fit-faces` from `f2l eval render-faces` photos."),
    render: Path = typer.Option(..., "--render", help="The `f2l eval render-faces` folder the photos came from."),
    out: Path = typer.Option(..., "--out", help="Output shard directory for the true-geometry twins."),
    json_out: JsonOut = False,
) -> None:
    """Swap fitted face geometry for the renderer's true mesh (same pixels and observations)."""
    from f2l.evaluation.evaluate import write_true_geometry_twins

    summary = write_true_geometry_twins(fitted, render, out)
    typer.echo(json.dumps(summary, indent=None if json_out else 2))
    if not summary["twins"]:
        fail("no fitted record matched a rendered case (photo stem = case id)")


def eval_real_cmd(
    render: Path = typer.Argument(..., help="The `f2l eval render-faces` folder (meta/, probes/)."),
    est: list[str] = typer.Option(..., "--est", help="An `f2l estimate` output folder, as DIR (fitted geometry) or LABEL=DIR."),
    out: Path = typer.Option(..., "--out", help="Where eval_real.md and eval_real_rows.csv go."),
    held_out: bool = typer.Option(False, "--held-out", help="No tuning part: every case reports (a set no default was chosen on, e.g. `render-faces --maps held-out`)."),
    fit_truth: list[str] = typer.Option([], "--fit-truth", help="Also fit this model to each true probe, no face (its family's oracle; repeatable; cached in OUT/truth_fits)."),
) -> None:
    """Table 2 analog on rendered faces: every model and the baselines, split tune/report, breakdowns."""
    from f2l.evaluation.eval_report import write_report
    from f2l.evaluation.evaluate import evaluate_real

    runs = {}
    for item in est:
        label, _, path = item.rpartition("=") if "=" in item else ("", "", item)
        runs[label or "fitted"] = Path(path)
    for label, path in runs.items():
        if not (path / "estimates.parquet").is_file():
            fail(f"{path}: no estimates.parquet (run `f2l estimate` first)")
    from f2l.models.registry import discover

    installed = discover()
    for name in fit_truth:
        if name not in installed or not installed[name].ok:
            fail(f"--fit-truth {name}: no such lighting model installed (`f2l models` lists them)")
    rows = evaluate_real(render, runs, fit_truth=tuple(dict.fromkeys(fit_truth)), fit_cache=out / "truth_fits")
    if not rows:
        fail(f"{render}: no rendered case found (meta/*.json)")
    if held_out:
        rows = [{**r, "split": "report"} for r in rows]
    summary = write_report(rows, out)
    typer.echo((out / "eval_real.md").read_text())
    typer.echo(json.dumps(summary))


def eval_real_geometry_cmd(
    eval_dir: Path = typer.Argument(..., help="The `make eval-real` folder (pbr/, fitted/, true_geometry/)."),
    model: list[str] = typer.Option(["sunsky"], "--model", "-m", help="Lighting models (repeatable)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Where geometry_share.md goes (default: EVAL_DIR)."),
    threads: int = typer.Option(2, help="Threads."),
) -> None:
    """The face fit's share of the error split into normals and occluders, and what is left on an
    ideal photo (f2l's own render of the truth on the true mesh; f2l.evaluation.geometry_share)."""
    from f2l.evaluation.geometry_share import geometry_share, write_share

    for sub in ("pbr", "fitted", "true_geometry"):
        if not (eval_dir / sub).is_dir():
            fail(f"{eval_dir / sub}: missing (run `make eval-real` first)")
    rows = geometry_share(eval_dir, list(model), threads=threads)
    if not rows:
        fail(f"{eval_dir}: no fitted face with a true-geometry twin")
    typer.echo(write_share(rows, out or eval_dir).read_text())


def eval_real_search_cmd(
    eval_dir: Path = typer.Argument(..., help="The `make eval-real` folder (pbr/, fitted/, true_geometry/)."),
    model: list[str] = typer.Option(["sunsky"], "--model", "-m", help="Compact-sun models (repeatable)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Where search_share.md goes (default: EVAL_DIR)."),
    limit: Optional[int] = typer.Option(None, "--limit", help="Only the first N clear cases."),
    held_out: bool = typer.Option(False, "--held-out", help="A set held out from tuning: one column over every case."),
    threads: int = typer.Option(2, help="Threads."),
) -> None:
    """The search's share of the sun error or the objective's: each fit run again from a start at the
    true sun, with and without the light prior (f2l.evaluation.search_share)."""
    from f2l.evaluation.search_share import search_share, write_search

    for sub in ("pbr", "fitted", "true_geometry"):
        if not (eval_dir / sub).is_dir():
            fail(f"{eval_dir / sub}: missing (run `make eval-real` first)")
    try:
        rows = search_share(eval_dir, list(model), threads=threads, limit=limit)
    except ValueError as exc:
        fail(str(exc))
    if not rows:
        fail(f"{eval_dir}: no clear case with a fitted face and a true-geometry twin")
    typer.echo(write_search(rows, out or eval_dir, held_out).read_text())


def eval_real_ablations_cmd(
    eval_dir: Path = typer.Argument(..., help="The `make eval-real` folder (eval_real_rows.csv, ablations/*/)."),
    n: int = typer.Option(32, "--n", help="Compare the first N cases (those the ablations re-rendered)."),
) -> None:
    """How much of each model's error each ablation (no specular, direct light only, canonical head, no clipping) removes."""
    from f2l.io.atomic import write_text_atomic
    from f2l.evaluation.eval_report import ablation_table

    if not (eval_dir / "eval_real_rows.csv").is_file():
        fail(f"{eval_dir}: no eval_real_rows.csv (run `make eval-real` first)")
    table = ablation_table(eval_dir, n)
    write_text_atomic(eval_dir / "ablations.md", table + "\n")
    typer.echo(table)


def eval_framings_cmd(
    render_dirs: list[Path] = typer.Argument(..., help="`f2l eval render-faces --framing ...` folders."),
    fitted: Path = typer.Option(..., "--fitted", help="`f2l fit-faces` of their photos (records + status table)."),
    est: Path = typer.Option(..., "--est", help="`f2l estimate` of the fitted records."),
    out: Optional[Path] = typer.Option(None, "--out", help="Write the table (Markdown) and the per-face rows (JSON) here."),
    json_out: JsonOut = False,
) -> None:
    """Accuracy against the face's size: detection, fitting and the §5.1 metrics per band of true face width (40-80, 80-160, 160-320, > 320 px) on framed render sets."""
    from f2l.evaluation.face_width import accuracy_by_face_width

    require_render_dirs(render_dirs)
    if not (Path(est) / "estimates.parquet").is_file():
        fail(f"{est}: no estimates.parquet")
    result = accuracy_by_face_width(render_dirs, fitted, est)
    if out is not None:
        from f2l.io.atomic import write_text_atomic

        Path(out).mkdir(parents=True, exist_ok=True)
        write_text_atomic(Path(out) / "accuracy_by_face_width.md", result["table"] + "\n")
        write_text_atomic(Path(out) / "accuracy_by_face_width.json", json.dumps(result["rows"], indent=1))
    typer.echo(json.dumps(result["rows"]) if json_out else result["table"])


def eval_groups_cmd(
    render_dirs: list[Path] = typer.Argument(..., help="`f2l eval render-faces --framing group` folders."),
    fitted: Path = typer.Option(..., "--fitted", help="`f2l fit-faces` of their photos."),
    model: str = typer.Option("sunsky", "--model", "-m", help="Lighting model."),
    sizes: list[int] = typer.Option([1, 2, 3, 5], "--faces", help="Group sizes to score (repeatable)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Write groups.md and groups.json here."),
    json_out: JsonOut = False,
) -> None:
    """Error against the number of faces: each photo's first n faces estimated one at a time and jointly (one light), scored against the true probe (§5.1 metrics), with the time of each."""
    from f2l.evaluation.groups import group_rows, group_table, write_group_report

    require_render_dirs(render_dirs)
    rows = group_rows(render_dirs, fitted, model, tuple(sizes),
                      progress=None if json_out else (lambda r: typer.echo(
                          f"{r['case']} n={r['n']}: Sun-ang {r['single'][0]:.1f} -> {r['joint'][0]:.1f}", err=True)))
    text = write_group_report(rows, out) if out is not None else group_table(rows)
    typer.echo(json.dumps(rows) if json_out else text)


def eval_sessions_cmd(
    render_dir: Path = typer.Argument(..., help="An `f2l eval render-faces --session-size K` folder."),
    fitted: Path = typer.Option(..., "--fitted", help="`f2l fit-faces` of its photos."),
    model: str = typer.Option("sunsky", "--model", "-m", help="Lighting model."),
    out: Optional[Path] = typer.Option(None, "--out", help="Write sessions.md and sessions.json here."),
    tag: Optional[Path] = typer.Option(None, "--tag", help="Also write the fitted records here with meta session and camera_yaw_deg (for `f2l estimate --joint session`)."),
    json_out: JsonOut = False,
) -> None:
    """Sessions (several photos, one light, known camera headings): each face estimated alone against its photo's true probe, and the session jointly in the first photo's frame against that photo's (§5.1 metrics), with the time of each."""
    from f2l.evaluation.sessions import session_rows, session_table, tag_records, write_session_report

    require_render_dirs([render_dir])
    if tag is not None:
        typer.echo(f"tagged {tag_records(render_dir, fitted, tag)} records in {tag}", err=True)
    rows = session_rows(render_dir, fitted, model,
                        progress=None if json_out else (lambda r: typer.echo(
                            f"{r['session']} ({r['faces']} faces): Sun-ang {r['single'][0]:.1f} -> {r['joint'][0]:.1f}",
                            err=True)))
    if not rows:
        fail(f"no session with two fitted photos in {render_dir} (render with --session-size)")
    text = write_session_report(rows, out) if out is not None else session_table(rows)
    typer.echo(json.dumps(rows) if json_out else text)


def eval_shade_cmd(
    render_dirs: list[Path] = typer.Argument(..., help="`f2l eval render-faces --framing group --shade-one` folders."),
    fitted: Path = typer.Option(..., "--fitted", help="`f2l fit-faces` of their photos."),
    model: str = typer.Option("sunsky", "--model", "-m", help="Lighting model."),
    out: Optional[Path] = typer.Option(None, "--out", help="Write shade.md and shade.json here."),
    json_out: JsonOut = False,
) -> None:
    """A face in an occluder's shadow: how often the joint estimate leaves it out, and the §5.1 metrics of the joint estimate with the check on, without that face, and with the check off."""
    from f2l.evaluation.shade import shade_rows, shade_table, write_shade_report

    require_render_dirs(render_dirs)
    rows = shade_rows(render_dirs, fitted, model,
                      progress=None if json_out else (lambda r: typer.echo(
                          f"{r['case']}: shaded face flagged {r['flagged']}, agreements {r['agreements']}", err=True)))
    if not rows:
        fail("no shaded photo (meta shaded_person) in " + ", ".join(map(str, render_dirs)))
    text = write_shade_report(rows, out) if out is not None else shade_table(rows)
    typer.echo(json.dumps(rows) if json_out else text)
