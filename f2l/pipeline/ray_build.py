"""``f2l build-dataset --executor ray``: the per-bracket, per-session, per-chart and per-photo
stages as Ray tasks (optional extra ``ray``).

The tasks run the very functions of the local build (:mod:`f2l.pipeline.probes`,
:mod:`f2l.pipeline.faces`) against the same content-keyed cache (``WORK/cache``), so a Ray build
writes the same entries, byte for byte, and the local pass that follows (pairing, shards, card,
publish) finds every entry made and only reads them. The work folder must be shared with the
workers (a local cluster, or a shared file system).

Streaming: every merge (per bracket), calibration (per chart) and fit-faces with its transport
(per face photo) is submitted at once; a session's sphere assembly is a task that takes its own
merges' results as arguments, so it starts when they are done and waits for nothing else.
Face photos go to an actor pool (one landmarker per actor, loaded once). A merge, sphere or
calibrate task that raises stops nothing: its entry is left unmade, and the local pass computes it
as a local build does and records the failure for that session or chart alone. Kill -9 and resume
behave as in the local build: an entry is published atomically when its task finishes, a killed
build leaves only temporary folders, which the next build sweeps, and a rerun computes only the
entries that are missing. Ray tasks can outlive a SIGKILLed driver by a moment; they carry the
build's token (``WORK/.build-token``, renewed by each build before its sweep) and publish nothing
once a new build has begun (:class:`~f2l.pipeline.cache.StaleBuild`).

``address``: an existing cluster; None starts a local one with ``workers`` CPUs for the build and
shuts it down afterwards (:func:`f2l.io.executor.ray_session`, as ``f2l estimate --executor ray``).
"""

from __future__ import annotations

from pathlib import Path

from f2l.io.executor import ExecutorUnavailable, ray_session
from f2l.io.progress import Progress, ProgressCallback

__all__ = ["prewarm", "ExecutorUnavailable"]


def _merge(work: str, token: str, root: str, plan, bid: str, params: dict) -> int:
    from f2l.pipeline import probes
    from f2l.pipeline.cache import Cache
    from f2l.pipeline.plan import SessionPlan

    counts: dict = {}
    probes.merge_session(Cache(work, token), Path(root), SessionPlan(plan.name, brackets={bid: plan.brackets[bid]}),
                         params, counts, {})
    return counts.get("computed", 0)


def _sphere(work: str, token: str, root: str, plan, params: dict, grid_hw, restore_sun: bool, *merged_counts) -> dict:
    from f2l.pipeline import probes
    from f2l.pipeline.cache import Cache

    cache, counts = Cache(work, token), {}
    merged = probes.merge_session(cache, Path(root), plan, params, {}, {})  # all made by the merge tasks
    probes.sphere_session(cache, plan, merged, tuple(grid_hw), counts, {}, restore_sun)
    return {"merge": sum(merged_counts), "sphere": counts.get("computed", 0)}


def _calibrate(work: str, token: str, root: str, row: dict, params: dict) -> int:
    from f2l.pipeline import faces
    from f2l.pipeline.cache import Cache

    counts: dict = {}
    faces.calibrate_chart(Cache(work, token), Path(root), row, params, counts, {})
    return counts.get("computed", 0)


class _Fitter:
    """One landmarker per actor; fits photos into the shared cache."""

    def __init__(self, work: str, token: str, root: str, fit: dict, transport: dict, grid_hw, landmarker_path) -> None:
        from f2l.pipeline.cache import Cache
        from f2l.pipeline.faces import FaceFitter

        self.fitter = FaceFitter(Cache(work, token), Path(root), fit, transport, tuple(grid_hw), landmarker_path)

    def fit(self, row: dict) -> int:
        counts: dict = {}
        self.fitter(row, counts, {})
        return counts.get("computed", 0)


def _finished(ray, ref) -> int:
    """Entries a finished merge task made (0 when it raised)."""
    try:
        return int(ray.get(ref))
    except Exception:  # noqa: BLE001
        return 0


def prewarm(spec, root: Path, work: Path, sessions: list, landmarker_path=None, *, token: str,
            address: str | None = None, workers: int = 2,
            progress: ProgressCallback | None = None) -> dict[str, int]:
    """Make every per-item cache entry of ``sessions`` on Ray; returns entries computed per stage,
    and under ``"failed"`` the number of merge/sphere or calibrate tasks that raised (none when
    nothing did). A task that raises stops nothing: its entry is left unmade, and the local pass
    that follows computes it as a local build does, recording the failure for that session or
    chart alone (:func:`f2l.pipeline.run._session_probe`). ``progress``: a callback told of each
    face photo fitted (:mod:`f2l.io.progress`)."""
    with ray_session(address, workers) as ray:
        try:
            from ray.util import ActorPool  # a part of ray, which ray_session has imported
        except ImportError as exc:  # a ray without its util package
            raise ExecutorUnavailable(f"ray is installed without ray.util: {exc}") from exc

        return _run(ray, ActorPool, spec, str(root), str(work), token, sessions, landmarker_path,
                    max(1, int(workers)), progress)


def _run(ray, ActorPool, spec, root: str, work: str, token: str, sessions: list, landmarker_path,  # noqa: N803
         workers: int, progress) -> dict:
    grid_hw = (spec.grid_height, spec.grid_width)
    merge_task, sphere_task, calibrate_task = (ray.remote(num_cpus=1)(f) for f in (_merge, _sphere, _calibrate))
    pending: dict = {}  # object ref -> stage
    merges_of: dict = {}  # sphere task's ref -> its merge tasks' refs
    if spec.has("merge"):
        params = spec.params("merge")
        restore_sun = bool(spec.params("sphere").get("restore_sun", False))
        for plan in sessions:
            if plan.given_probe is not None or not plan.brackets or "merge" in plan.skipped:
                continue
            merges = [merge_task.remote(work, token, root, plan, bid, params) for bid in sorted(plan.brackets)]
            ref = sphere_task.remote(work, token, root, plan, params, grid_hw, restore_sun, *merges)
            pending[ref], merges_of[ref] = "sphere", merges
    if spec.has("calibrate"):
        for plan in sessions:
            for row in plan.charts:
                pending[calibrate_task.remote(work, token, root, row, spec.params("calibrate"))] = "calibrate"
    rows = [row for plan in sessions for row in plan.faces]
    counts = {"merge": 0, "sphere": 0, "calibrate": 0, "fit-faces": 0}
    # an actor holds its CPU share for its whole life: half a CPU each, so that ``workers`` actors
    # leave room for the merge, sphere and chart tasks (whole actors would starve them: deadlock)
    fitter = ray.remote(num_cpus=0.5)(_Fitter)
    actors = [fitter.remote(work, token, root, spec.params("fit-faces"), spec.params("transport"), grid_hw,
                            landmarker_path)
              for _ in range(min(workers, max(1, len(rows))))] if rows else []
    pool = ActorPool(actors) if actors else None
    bar = Progress(progress, "fit-faces (ray)", "photo", len(rows))
    for row in rows:
        pool.submit(lambda actor, r: actor.fit.remote(r), row)
    while pending or (pool is not None and pool.has_next()):  # both streams, as results arrive
        if pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=0.05)
            for ref in done:
                stage = pending.pop(ref)
                try:
                    value = ray.get(ref)
                except Exception:  # noqa: BLE001 - this session's or chart's failure, not the build's
                    # no entry was made: the local pass computes it again and records the failure
                    # for this item alone, as a local build does (run._session_probe); the others go on
                    counts["failed"] = counts.get("failed", 0) + 1
                    if stage == "sphere":  # the merges that did finish made their entries
                        counts["merge"] += sum(_finished(ray, m) for m in merges_of[ref])
                    continue
                if stage == "sphere":
                    counts["merge"] += value["merge"]
                    counts["sphere"] += value["sphere"]
                else:
                    counts[stage] += value
        if pool is not None and pool.has_next():
            try:
                counts["fit-faces"] += pool.get_next_unordered(timeout=0.05)
            except TimeoutError:
                continue
            bar.advance(1)
    return counts
