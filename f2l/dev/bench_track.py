"""Time decoding and face tracking on a 1280×720 clip: ``python -m f2l.dev.bench_track``.

The clip is made here from real photographs: scikit-image's ``astronaut`` (a NASA portrait,
public domain), cropped to head and shoulders, pasted onto ``coffee`` (no face) scaled to the
frame, moving across it and growing (face ~110 → ~170 px wide), ``frames`` frames at 25 fps,
written with OpenCV's ``VideoWriter`` (MPEG-4 part 2) into a temporary folder.

Reported, in ms per frame (the median and the mean over the clip):

* **decode** — :func:`f2l.video.decode.read_frames` alone (demux, decode, rotate, BGR → RGB);
* **follow** — :meth:`FaceTracker.update` on frames without detection (one landmark inference
  per face on the ROI from the last landmarks, the pose, the rows);
* **keyframe** — :meth:`FaceTracker.update` on the frames the detector ran on (the tiled
  detector over the whole frame, plus the still-image landmarks of a new face);
* **total** — decode + track per frame, end to end (:func:`track_clip`), and its frames/s;
* **landmark error** — the tracked landmarks' distance from the still-image landmarker's
  (:class:`~f2l.face.landmarker.FaceLandmarker` on the same decoded frame: detection, crops,
  one refining pass) on every 10th frame, median and 95th percentile, px.

LiteRT runs on one thread. The machine is shared: compare ratios measured in one run.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np


def make_clip(path: Path, frames: int = 120, size: tuple[int, int] = (1280, 720), fps: float = 25.0) -> Path:
    """The benchmark's clip (see the module docstring), written to ``path``."""
    import cv2

    try:
        import skimage.data as skdata
    except ImportError as exc:  # pragma: no cover - a test extra
        raise RuntimeError("bench_track needs scikit-image's sample photos: pip install 'f2l[test]' "
                           "(the README's setup installs it)") from exc
    w, h = size
    background = cv2.resize(skdata.coffee(), (w, h), interpolation=cv2.INTER_CUBIC)
    head = skdata.astronaut()[0:330, 100:350]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), fps, (w, h))
    for i in range(frames):
        t = i / max(1, frames - 1)
        k = h / 720  # the layout is that of 1280×720, scaled to the frame
        scale = k * (1.2 + 0.6 * t)
        sprite = cv2.resize(head, (round(head.shape[1] * scale), round(head.shape[0] * scale)),
                            interpolation=cv2.INTER_AREA)
        x, y = round(k * (100 + 700 * t)), round(k * (60 + 40 * np.sin(2 * np.pi * t)))
        img = background.copy()
        sh, sw = min(sprite.shape[0], h - y), min(sprite.shape[1], w - x)
        img[y:y + sh, x:x + sw] = sprite[:sh, :sw]
        writer.write(cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    writer.release()
    return path


def run_bench(frames: int = 120, size: tuple[int, int] = (1280, 720), keyframe_every: int = 30,
              predict_motion: bool = True, check_every: int = 10) -> dict:
    """The timings (see the module docstring) as a dict of ms/frame figures and counts, and the
    tracked landmarks' distance from the still-image landmarker's on every ``check_every``-th
    frame (median and 95th percentile over landmarks and frames, px)."""
    from f2l.face.landmarker import FaceLandmarker
    from f2l.video.decode import read_frames
    from f2l.video.track import FaceTracker

    with tempfile.TemporaryDirectory() as tmp:
        clip = make_clip(Path(tmp) / "bench.mp4", frames, size)
        t0 = time.perf_counter()
        landmarker = FaceLandmarker(threads=1)
        startup_s = time.perf_counter() - t0
        decode_ms = []
        t = time.perf_counter()
        for _ in read_frames(clip):
            now = time.perf_counter()
            decode_ms.append((now - t) * 1e3)
            t = now
        tracker = FaceTracker(landmarker, keyframe_every=keyframe_every, predict_motion=predict_motion)
        follow_ms, keyframe_ms, total_ms, statuses, checked = [], [], [], [], []
        t = time.perf_counter()
        for index, time_s, rgb in read_frames(clip):
            t1 = time.perf_counter()
            rows = tracker.update(rgb, index, time_s)
            t2 = time.perf_counter()
            (keyframe_ms if rows and rows[0].keyframe else follow_ms).append((t2 - t1) * 1e3)
            total_ms.append((t2 - t) * 1e3)
            statuses.extend(r.status for r in rows)
            if index % check_every == 0 and rows and rows[0].landmarks is not None:
                checked.append((rgb, rows[0].landmarks))
            t = time.perf_counter()
        errors, widths = [], []
        for rgb, tracked in checked:
            still = landmarker(rgb, max_faces=1)
            if still:
                errors.append(np.linalg.norm(tracked[:468, :2] - still[0].points[:468, :2], axis=1))
                widths.append(float(np.ptp(still[0].points[:468, 0])))
    total = statistics.fmean(total_ms)
    err = np.concatenate(errors) if errors else np.array([np.nan])
    return {"size": f"{size[0]}x{size[1]}", "frames": frames, "keyframe_every": keyframe_every,
            "predict_motion": predict_motion, "startup_s": round(startup_s, 3),
            "decode_ms": _stats(decode_ms), "follow_ms": _stats(follow_ms),
            "keyframe_ms": _stats(keyframe_ms), "keyframes": len(keyframe_ms),
            "total_ms": _stats(total_ms), "fps": round(1e3 / total, 1),
            "ok_rows": statuses.count("ok"), "rows": len(statuses), "people": tracker._next_person,
            "landmark_err_px": {"median": round(float(np.median(err)), 2),
                                "p95": round(float(np.percentile(err, 95)), 2)},
            "face_width_px": round(float(np.median(widths)), 1) if widths else None}


def _stats(ms: list[float]) -> dict:
    return {"median": round(statistics.median(ms), 2), "mean": round(statistics.fmean(ms), 2)} if ms else {}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=120)
    parser.add_argument("--width", type=int, default=1280)
    parser.add_argument("--height", type=int, default=720)
    parser.add_argument("--keyframe-every", type=int, default=30)
    parser.add_argument("--no-predict-motion", action="store_true",
                        help="follow from the last ROI as it is (no constant-velocity step)")
    args = parser.parse_args(argv)
    r = run_bench(args.frames, (args.width, args.height), args.keyframe_every, not args.no_predict_motion)
    print(f"clip {r['size']}, {r['frames']} frames, one face; detector every {r['keyframe_every']} frames "
          f"({r['keyframes']} keyframes); landmarker start-up {r['startup_s']} s")
    print("| stage | median ms/frame | mean ms/frame |\n| --- | --- | --- |")
    for key in ("decode_ms", "follow_ms", "keyframe_ms", "total_ms"):
        print(f"| {key[:-3]} | {r[key].get('median', '-')} | {r[key].get('mean', '-')} |")
    print(f"total: {r['fps']} frames/s; rows ok {r['ok_rows']} of {r['rows']}; people {r['people']}")
    e = r["landmark_err_px"]
    print(f"tracked vs still-image landmarks (every 10th frame, face ~{r['face_width_px']} px wide): "
          f"median {e['median']} px, 95th percentile {e['p95']} px; predict_motion={r['predict_motion']}")


if __name__ == "__main__":
    main()
