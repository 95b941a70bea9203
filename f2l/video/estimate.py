"""Light from a clip: one light per window of frames, restarted at cuts and sudden changes.

A face in a clip turns and nods under the same sky, so its frames are several views of one light
(:mod:`f2l.estimate.joint`). Per clip (:func:`estimate_clip`):

1. **Track** each face (:mod:`f2l.video.track`) and watch for **changes** (:mod:`f2l.video.changes`): a cut or a change of
   the whole scene's light (the frame's colour histogram outside the faces' boxes, the same region
   in both frames, moves by more than ``cut_distance`` in L1 between two frames), or a sudden
   change of the light on a face (its mean linear luminance over patches at its 468 landmarks
   jumps by more than ``change_ratio`` against the median of its last three frames: a cloud over
   the sun, walking into shade). Each change starts a new **segment**; nothing but the sun's
   direction is shared across segments, and that only where their suns agree (step 4).
2. **Sample** a face every ``sample_every`` frames (and at once in a new segment; every
   ``cold_sample_every`` frames, if more often, until the segment's first light), fitted as a
   photo's face is (:func:`f2l.face.fit.fit_face`, at ``resolution`` px) but with its transport
   read from the head's cached table (:mod:`f2l.video.head`) instead of ray casting. The window
   holds the segment's samples of the last ``window_s`` seconds, at most ``max_window_faces``
   (every person's: one camera, one sky); over that, the sample whose head pose is nearest
   another's leaves (a face seen from several sides constrains the sun).
3. **Estimate** the window's light. The segment's first light waits (the clip is processed
   offline) for samples ``(cold_faces - 1) * sample_every`` frames apart (the time ``cold_faces``
   samples take), or ``cold_span_s`` apart, or the segment's end, and keeps the most varied
   ``max_window_faces`` of its denser samples; it
   is the full joint estimate (sun search, disagreeing faces left out, elevation profile), and so is
   the window's light every ``refit_every`` new samples after it. With ``warm_refit`` the later
   windows are instead refitted from the last light (:func:`f2l.estimate.joint.refit_joint`,
   ``warm_iters`` L-BFGS iterations) under a prior on how fast the sun can move in the camera's
   frame: ``temporal_weight`` · ½ |s − s_last|² / σ², σ² = σ₀² + (``light_rate_deg_s`` · Δt)²
   (faster, but it drifted on long clips). One person's samples share one skin albedo
   (``tie_albedo``): how the same skin brightens and darkens as the head turns is what the frames
   tell about the light.
4. **One sun where the segments agree** (:mod:`f2l.video.sun_share`). A cloud over the sun, walking into shade or an exposure
   jump starts a segment but moves no sun in the camera's frame; a cut may (or may not: the
   colours of a frame cannot tell a cut from a cloud that darkens the whole scene). So two
   consecutive segments whose suns agree within their 90% cones (the last window of the one, the
   first of the next: the angle between their suns at most the smaller r_90) are taken to share
   one sun (``share_agreeing_suns``, :class:`SunSharing`): those two windows are refitted from
   their lights with the sun held (a prior of ``share_sigma_deg``; the sky's and the sun's
   strengths stay each window's own) at the mean of the suns of the run's windows at its changes so
   far, each weighted by 1 / r_68². Windows without cones (a warm refit, a model without them)
   share nothing; the windows inside a long segment keep their own suns.
5. **Every frame** gets the light of its segment, interpolated in time between the estimates
   around it (each placed at the mean time of its window; the sun's direction interpolated on
   the sphere), so a static light does not jitter and a frame is never lit by another segment.

Assumed: a static or slowly panning camera (the light is held in the camera's frame) and a fixed
exposure within a segment (an exposure jump reads as a light change and starts a segment). Flags:
a person's frames carry the tracker's status (lost, covered, turned, cut off, too small) or the
fit's refusal; a clip without any usable face gives no light.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from f2l.lighting.grid import LatLongGrid
from f2l.video.changes import ChangeDetector
from f2l.video.sun_share import SunSharing, sample_problem, sun_prior

__all__ = ["Sample", "SampleEstimate", "VideoOptions", "ClipLight", "estimate_clip_light", "interpolate_params",
           "default_grid"]



@dataclass(frozen=True)
class VideoOptions:
    """Settings of :func:`estimate_clip_light` (module docstring)."""

    model: str = "sunsky"
    sample_every: int = 8  # frames between a face's samples
    # before a segment's first light, a face is sampled this often if more often than
    # ``sample_every`` (the first light keeps the most varied ``max_window_faces``); 4 was tried and
    # dropped (docs/experiments/video_estimate.md, "Denser samples before the first light")
    cold_sample_every: int = 8
    window_s: float = 4.0  # samples of the last so many seconds share one light
    max_window_faces: int = 6
    cold_faces: int = 6  # a segment's first light waits for this many samples, or
    cold_span_s: float = 2.0  # for samples this far apart (or the segment's end)
    tie_albedo: bool = True  # one skin albedo per person across its samples
    resolution: int = 104  # working px of a sampled face (as a photo's)
    warm_iters: int = 12
    refit_every: int = 6  # after a segment's first light, a new window once so many new samples have come
    # later windows: full joint estimates (False), or refits from the last light (refit_joint, under
    # the temporal prior): faster, but on 10 s clips they drifted (docs/experiments/video_estimate.md)
    warm_refit: bool = False
    light_rate_deg_s: float = 2.0  # how fast the sun may move in the camera's frame
    temporal_sigma_deg: float = 2.0  # sigma_0 of the temporal prior
    temporal_weight: float = 1e-2
    # consecutive segments whose suns agree within their 90% cones share one sun (module docstring, step 4)
    share_agreeing_suns: bool = True
    share_sigma_deg: float = 0.25
    change_ratio: float = 1.8
    cut_distance: float = 0.5
    min_face_px: float = 40.0
    keyframe_every: int = 30
    focal_35mm_mm: float = 50.0  # the camera's 35 mm-equivalent focal length (clips rarely say)
    focal_px: float | None = None  # the focal length in px, where known (overrides focal_35mm_mm)

    def __post_init__(self) -> None:
        if min(self.sample_every, self.cold_sample_every, self.max_window_faces, self.warm_iters, self.cold_faces,
               self.refit_every) < 1:
            raise ValueError("sample_every, cold_sample_every, max_window_faces, cold_faces, refit_every and "
                             "warm_iters must be >= 1")
        if self.change_ratio <= 1.0 or self.window_s <= 0:
            raise ValueError("change_ratio must be > 1 and window_s > 0")


@dataclass
class Sample:
    """One sampled face: its frame, person, observation and pixel positions."""

    frame: int
    time_s: float
    person: int
    observation: object
    pixel_rc: np.ndarray
    segment: int
    yaw_deg: float = 0.0
    pitch_deg: float = 0.0
    problem: object = None  # its FaceProblem for warm refits (built on first use)
    row: dict = field(default_factory=dict)  # its frame's row in the table


@dataclass
class SampleEstimate:
    """The light of one window: fitted at ``frame`` from ``window`` (frame indices of its samples)."""

    frame: int
    time_s: float  # the mean time of its window's samples
    segment: int
    params: np.ndarray
    sun_direction: np.ndarray | None
    ground_albedo: float | None
    window: list[int]
    persons: list[int]
    residual: dict  # (frame, person) -> the face's data term under this light
    cold: bool
    runtime_s: float
    # the sun's cones of a full joint estimate (f2l.estimate.uncertainty): r_68, r_90 (deg) and the
    # predicted relit-scene MAE (s); None for a warm refit (no search)
    cones: tuple[float, float, float] | None = None
    samples: list = field(default_factory=list)  # the window's samples it used (for a refit)


@dataclass
class ClipLight:
    """What :func:`estimate_clip_light` found: per-frame rows, the window estimates, timings."""

    rows: list[dict]
    estimates: list[SampleEstimate]
    segments: list[tuple[int, str]]  # (first frame, why it started)
    fps: float
    width: int
    height: int
    timings: dict = field(default_factory=dict)
    param_names: list[str] = field(default_factory=list)



def _temporal_prior(model, last: SampleEstimate, dt_s: float, options: VideoOptions):
    """The prior on the sun's move since ``last`` (module docstring, step 3), or None."""
    if last.sun_direction is None or not hasattr(model, "sun_angles"):
        return None
    sigma_deg = math.hypot(options.temporal_sigma_deg, options.light_rate_deg_s * max(dt_s, 0.0))
    return sun_prior(model, last.sun_direction, sigma_deg, options.temporal_weight)


def interpolate_params(model, a: SampleEstimate, b: SampleEstimate, time_s: float) -> np.ndarray:
    """The light at ``time_s`` between two estimates of one segment: parameters linear in time,
    the sun's direction along the great circle (its angles set from it)."""
    span = b.time_s - a.time_s
    t = 0.0 if span <= 0 else float(np.clip((time_s - a.time_s) / span, 0.0, 1.0))
    params = (1.0 - t) * a.params + t * b.params
    if a.sun_direction is not None and b.sun_direction is not None and hasattr(model, "sun_angles"):
        from f2l.lighting.grid import angles_from_direction

        u, v = np.asarray(a.sun_direction, np.float64), np.asarray(b.sun_direction, np.float64)
        omega = math.acos(float(np.clip(u @ v, -1.0, 1.0)))
        d = u if omega < 1e-9 else (math.sin((1 - t) * omega) * u + math.sin(t * omega) * v) / math.sin(omega)
        el, az = angles_from_direction(d / np.linalg.norm(d))
        params[model.sun_angles.elevation] = float(el)
        params[model.sun_angles.azimuth] = float(az)
    return params


def _fit_options(resolution: int, grid: LatLongGrid, min_face_px: float):
    from f2l.pipeline.faces import fit_options
    from f2l.pipeline.spec import load_pipeline

    spec = load_pipeline()
    fit = dict(spec.params("fit-faces"))
    fit["min_face_px"] = float(min_face_px)
    options = fit_options(fit, spec.params("transport"), (grid.height, grid.width))
    return dataclasses.replace(options, resolution=int(resolution))


def default_grid() -> LatLongGrid:
    """The pipeline's lighting grid."""
    from f2l.pipeline.spec import load_pipeline

    spec = load_pipeline()
    return LatLongGrid(spec.grid_height, spec.grid_width)


def estimate_clip_light(frames, options: VideoOptions = VideoOptions(), *, fps: float, width: int, height: int,
                        head=None, grid: LatLongGrid | None = None, config=None, progress=None,
                        total_frames: int | None = None) -> ClipLight:
    """The light of every frame of a tracked clip (module docstring).

    ``frames``: :class:`f2l.video.track.TrackedFrame` in order (``track_clip``). ``head``: a
    :class:`f2l.video.head.HeadTransport` (default: the cached one for ``grid``). ``config``: the
    estimator's :class:`~f2l.estimate.config.EstimatorConfig`. ``progress``: a
    :data:`f2l.io.progress.ProgressCallback` (one event a frame, of ``total_frames``)."""
    from f2l.estimate.config import EstimatorConfig
    from f2l.estimate.joint import JointUnsupported, estimate_joint, refit_joint
    from f2l.estimate.observation import EstimationError, FaceObservation
    from f2l.estimate.record import _get_model
    from f2l.face.fit import FaceFit, fit_face
    from f2l.io.photo.core import Photo
    from f2l.io.photo.exif import DIAGONAL_35MM_MM
    from f2l.video.head import cached_head_transport

    from f2l.io.progress import Progress

    t_start = time.perf_counter()
    report = Progress(progress, "video", "frame", total_frames)
    grid = grid or default_grid()
    head = head or cached_head_transport(grid)
    model = _get_model(options.model, grid)
    cfg = config or EstimatorConfig()
    warm_cfg = dataclasses.replace(cfg, sun_elevation_profile_deg=(), max_iter=options.warm_iters)
    fit_opts = _fit_options(options.resolution, grid, options.min_face_px)
    focal_px = options.focal_px or options.focal_35mm_mm / DIAGONAL_35MM_MM * math.hypot(width, height)
    detector = ChangeDetector(options.cut_distance, options.change_ratio)
    visibility = head.for_fit()

    rows: list[dict] = []
    estimates: list[SampleEstimate] = []
    segments: list[tuple[int, str]] = []
    window: deque[Sample] = deque()
    last_sample: dict[int, int] = {}
    first_sample_frame: int | None = None  # the segment's first sample
    cold_span_frames = (options.cold_faces - 1) * options.sample_every
    segment = -1
    spent = {"track_s": 0.0, "fit_s": 0.0, "estimate_s": 0.0, "change_s": 0.0}
    n_frames = 0
    t_track = time.perf_counter()
    last_frame = None

    sharing = (SunSharing(model, warm_cfg, options, refit_joint, (JointUnsupported, EstimationError))
               if options.share_agreeing_suns else None)

    def run_window(tf) -> None:
        t0 = time.perf_counter()
        est = _estimate_window(list(window), model, cfg, warm_cfg, estimates, segment, tf, options,
                               estimate_joint, refit_joint, (JointUnsupported, EstimationError))
        spent["estimate_s"] += time.perf_counter() - t0
        if est is not None:
            estimates.append(est)
            if sharing is not None:
                t0 = time.perf_counter()
                sharing.add(est, estimates[-2] if len(estimates) > 1 else None)
                spent["estimate_s"] += time.perf_counter() - t0
            else:
                est.samples = []
            return
        for sample in window:
            if sample.row.get("status") == "ok":
                sample.row.update(status="no_estimate", message="the window's faces gave no estimate")

    def flush(tf) -> None:
        if window and not (estimates and estimates[-1].segment == segment):
            run_window(tf)

    for tf in frames:
        last_frame = tf
        spent["track_s"] += time.perf_counter() - t_track
        n_frames += 1
        t0 = time.perf_counter()
        why = detector.update(tf.image, tf.faces)
        spent["change_s"] += time.perf_counter() - t0
        if segment < 0 or why is not None:
            if why is not None:
                flush(tf)  # the last segment's light, if it waited for more faces and never had them
                report.note(f"frame {tf.index}: new segment ({why})")
            segment += 1
            segments.append((tf.index, why or "start"))
            window.clear()
            last_sample.clear()
            first_sample_frame = None
        lit = bool(estimates) and estimates[-1].segment == segment
        every = options.sample_every if lit else min(options.cold_sample_every, options.sample_every)
        photo = None
        new = False
        frame_rows = []
        for face in tf.faces:
            row = {"frame": tf.index, "time_s": tf.time_s, "person": face.person, "status": face.status,
                   "message": face.reason, "segment": segment, "sample": False, "box": list(map(float, face.box)),
                   "yaw_deg": face.yaw_deg, "pitch_deg": face.pitch_deg}
            frame_rows.append(row)
            if face.status != "ok" or face.landmarks is None:
                continue
            due = face.person not in last_sample or tf.index - last_sample[face.person] >= every
            if not due:
                continue
            t0 = time.perf_counter()
            if photo is None:
                photo = Photo(path=f"frame {tf.index}", kind="video", codes=tf.image, focal_px=focal_px,
                              focal_source="option" if options.focal_px or options.focal_35mm_mm != 50.0
                              else "default", orientation=1, exif={})
            fitted = fit_face(photo, face.landmarks, face.person, fit_opts, visibility=visibility)
            spent["fit_s"] += time.perf_counter() - t0
            last_sample[face.person] = tf.index
            if not isinstance(fitted, FaceFit):
                row.update(status=fitted.reason, message=fitted.message)
                continue
            obs = FaceObservation(fitted.normals, fitted.observed_rgb, fitted.mask, fitted.visibility_bits, grid,
                                  f"{tf.index}:{face.person}", fitted.points)
            window.append(Sample(tf.index, tf.time_s, face.person, obs, fitted.pixel_rc, segment,
                                 yaw_deg=fitted.head.yaw_deg, pitch_deg=fitted.head.pitch_deg, row=row))
            row["sample"] = True
            new = True
            if first_sample_frame is None:
                first_sample_frame = tf.index
        rows.extend(frame_rows)
        if new:
            while window and tf.time_s - window[0].time_s > options.window_s:
                window.popleft()
            while len(window) > options.max_window_faces:
                del window[_most_redundant(window)]
            # offline: a segment's first light waits for samples over the time ``cold_faces`` samples
            # take, or ``cold_span_s`` seconds of them (every frame of the segment then gets it);
            # later ones follow every ``refit_every`` new samples
            span = window[-1].time_s - window[0].time_s if window else 0.0
            fresh = sum(1 for w in window if w.frame > estimates[-1].frame) if lit else 0
            cold_due = (window and first_sample_frame is not None
                        and (window[-1].frame - first_sample_frame >= cold_span_frames
                             or (len(window) > 1 and span >= options.cold_span_s)))
            if fresh >= options.refit_every if lit else cold_due:
                run_window(tf)
        report.advance()
        t_track = time.perf_counter()
    if last_frame is not None:
        flush(last_frame)
    if estimates:
        estimates[-1].samples = []
    _fill_rows(rows, estimates, model)
    total = time.perf_counter() - t_start
    timings = {**{k: round(v, 4) for k, v in spent.items()}, "total_s": round(total, 4), "frames": n_frames,
               "frames_per_s": round(n_frames / total, 3) if total > 0 else None,
               "estimates": len(estimates), "head_build_s": round(getattr(head, "build_s", 0.0), 4)}
    return ClipLight(rows=rows, estimates=estimates, segments=segments, fps=fps, width=width, height=height,
                     timings=timings, param_names=list(model.param_names))


def _estimate_window(window: list[Sample], model, cfg, warm_cfg, estimates: list[SampleEstimate], segment: int,
                     tf, options: VideoOptions, estimate_joint, refit_joint, errors) -> SampleEstimate | None:
    """The light of the window's samples: cold at a segment's start, warm after (module docstring)."""
    if not window:
        return None
    t0 = time.perf_counter()
    obs = [s.observation for s in window]
    rc = [s.pixel_rc for s in window]
    last = estimates[-1] if estimates and estimates[-1].segment == segment else None
    try:
        # one person's samples share one skin albedo: how the same skin brightens and darkens as
        # the head turns is what the frames tell about the light
        persons = [s.person for s in window] if options.tie_albedo else None
        if last is None or not options.warm_refit:
            joint = estimate_joint(obs, model, cfg, pixel_rc=rc, albedo_group=persons, share_parts=True)
            result, shares = joint.result, joint.faces
        else:
            prior = _temporal_prior(model, last, tf.time_s - last.time_s, options)
            result, shares = refit_joint(obs, model, last.params, warm_cfg, extra_prior=prior, pixel_rc=rc,
                                         problems=[sample_problem(s, model, warm_cfg) for s in window], albedo_group=persons)
    except errors:
        return None
    used = [s for s, share in zip(window, shares) if share.used]
    u = getattr(result, "sun_uncertainty", None)
    cones = None if u is None else (float(u.cone68_deg), float(u.cone90_deg), float(u.predicted_mae_s))
    residual = {(s.frame, s.person): share.data for s, share in zip(window, shares) if share.data is not None}
    return SampleEstimate(frame=tf.index, time_s=float(np.mean([s.time_s for s in used] or [tf.time_s])),
                          segment=segment, params=np.asarray(result.params, np.float64),
                          sun_direction=None if result.sun_direction is None else np.asarray(result.sun_direction),
                          ground_albedo=result.ground_albedo, window=[s.frame for s in used],
                          persons=[s.person for s in used], residual=residual, cold=last is None,
                          runtime_s=time.perf_counter() - t0, cones=cones, samples=used)


def _most_redundant(window) -> int:
    """The index of the sample (not the newest) whose head pose is nearest another's: the window
    keeps the poses that differ most (a face seen from several sides constrains the sun)."""
    poses = np.array([[s.yaw_deg, s.pitch_deg] for s in window], np.float64)
    poses = np.nan_to_num(poses)
    d = np.linalg.norm(poses[:, None] - poses[None], axis=2) + np.diag(np.full(len(window), np.inf))
    nearest = d.min(1)[:-1]  # the newest stays
    return int(np.argmin(nearest + 1e-9 * np.arange(len(nearest))))  # ties: the oldest


def _fill_rows(rows: list[dict], estimates: list[SampleEstimate], model) -> None:
    """Each row's light: interpolated between its segment's estimates (module docstring, step 4)."""
    from f2l.lighting.grid import angles_from_direction

    by_segment: dict[int, list[SampleEstimate]] = {}
    for e in estimates:
        by_segment.setdefault(e.segment, []).append(e)
    for row in rows:
        seg = by_segment.get(row["segment"])
        row.update(params=None, sun_direction=None, sun_elevation_deg=None, sun_azimuth_deg=None, window=None,
                   residual=None, ground_albedo=None, estimate_frame=None, sun_cone68_deg=None, sun_cone90_deg=None,
                   predicted_mae_s=None)
        if not seg:
            continue
        times = np.array([e.time_s for e in seg])
        k = int(np.searchsorted(times, row["time_s"], side="right"))
        a, b = seg[max(k - 1, 0)], seg[min(k, len(seg) - 1)]
        params = interpolate_params(model, a, b, row["time_s"])
        near = a if abs(row["time_s"] - a.time_s) <= abs(b.time_s - row["time_s"]) else b
        sun = model.sun_direction(params) if hasattr(model, "sun_direction") else None
        row.update(params=[float(v) for v in params], window=list(near.window), estimate_frame=near.frame,
                   ground_albedo=near.ground_albedo, residual=near.residual.get((row["frame"], row["person"])))
        if near.cones is not None:  # the nearest window's cones (a frame between two: the nearer's)
            row.update(sun_cone68_deg=near.cones[0], sun_cone90_deg=near.cones[1], predicted_mae_s=near.cones[2])
        if sun is not None:
            el, az = angles_from_direction(np.asarray(sun, np.float64))
            row.update(sun_direction=[float(v) for v in sun], sun_elevation_deg=math.degrees(float(el)),
                       sun_azimuth_deg=math.degrees(float(az)))
