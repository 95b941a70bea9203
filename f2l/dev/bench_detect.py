"""``f2l dev bench-detect``: face detection's recall by face width, false detections, and time by photo size.

Real photographs, composited as people frame them (scikit-image's data, BSD-3; the astronaut is a
NASA portrait, public domain; the backgrounds hold no face):

* **recall** — ``photos`` composites of 0.3–12 MP (aspect 1:1 to 16:9, either orientation), each
  with 1–6 copies of the astronaut's head and shoulders on a real background, the face 40 px to
  35% of the long side (log-uniform), mirrored or not, 0.5–1.3× brightness, never overlapping. A
  true face is found when a kept detection overlaps its box by IoU > 0.4. Reported per band of
  face width (the detector box's: 40–80, 80–160, 160–320, > 320 px);
* **false detections** — ``negatives`` face-free photos (coffee, chelsea, rocket, the two
  motorcycle views, the Hubble deep field, retina, immunohistochemistry, colour wheel) at
  0.7–5× their size, mirrored at random: detector hits, and faces left after the landmark model's
  presence check and the confirmation of doubted hits and candidates (what ``fit-faces`` would
  fit; ``confirmed``: how many of the faces, true or false, needed the confirmation);
* **time** — detection (windows + merge) and detection + landmarks on one composite at each size
  in ``sizes_mp``, the median of ``repeats`` runs after a warm-up, one LiteRT thread.

``detector`` picks the model the windows run: ``full_range`` (the shipped one) or
``short_range`` (the bundle's 128² detector, tiled the same way), to reproduce the choice
(``docs/experiments/face_detection.md``). Deterministic for a seed.
"""

from __future__ import annotations

import math
import resource
import time

import numpy as np

from f2l.face.detector import SHORT_RANGE, TiledDetector, iou
from f2l.face.landmarker import FaceLandmarker

BANDS = ((40, 80), (80, 160), (160, 320), (320, math.inf))
ASTRONAUT_FACE = np.array([172.0, 67.0, 279.0, 175.0])  # detected at 512 px (x0, y0, x1, y1)
HEAD_AND_SHOULDERS = (100, 10, 350, 330)
NEGATIVES = ("coffee", "chelsea", "rocket", "stereo_motorcycle", "stereo_motorcycle_right",
             "hubble_deep_field", "retina", "immunohistochemistry", "colorwheel")


def _skdata():
    try:
        import skimage.data as skdata
    except ImportError as exc:  # pragma: no cover - a test extra
        raise RuntimeError("bench-detect needs scikit-image's sample photos: pip install 'f2l[test]' "
                           "(the README's setup installs it)") from exc
    return skdata


def _negative(skdata, name: str) -> np.ndarray:
    if name.startswith("stereo_motorcycle"):
        pair = skdata.stereo_motorcycle()
        return pair[1] if name.endswith("right") else pair[0]
    return getattr(skdata, name)()


def _resize(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    import cv2

    interp = cv2.INTER_AREA if size[0] < image.shape[1] else cv2.INTER_CUBIC
    return cv2.resize(np.ascontiguousarray(image), size, interpolation=interp)


def composite(rng: np.random.Generator, long_side: int, astronaut: np.ndarray, backgrounds: list[np.ndarray],
              max_faces: int = 6, size: tuple[int, int] | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """A photo of ``long_side`` px (or exactly ``size`` (w, h)) with 1..max_faces astronauts on a real
    background: (RGB uint8, true face boxes in photo px)."""
    aspect = float(rng.choice([1.0, 4 / 3, 3 / 2, 16 / 9]))
    w, h = long_side, max(64, round(long_side / aspect))
    if rng.random() < 0.3:
        w, h = h, w
    if size is not None:
        w, h = size
    canvas = _resize(backgrounds[int(rng.integers(len(backgrounds)))], (w, h)).copy()
    x0, y0, x1, y1 = HEAD_AND_SHOULDERS
    crop = astronaut[y0:y1, x0:x1]
    face0 = ASTRONAUT_FACE - [x0, y0, x0, y0]
    truths: list[np.ndarray] = []
    rects: list[np.ndarray] = []
    for _ in range(int(rng.integers(1, max_faces + 1))):
        top = min(0.35 * max(w, h), 0.45 * min(w, h))
        if top <= 40:
            break
        f = float(np.exp(rng.uniform(np.log(40.0), np.log(top))))
        s = f / (face0[2] - face0[0])
        im, face = crop, face0
        if rng.random() < 0.5:
            im = crop[:, ::-1]
            face = np.array([crop.shape[1] - face0[2], face0[1], crop.shape[1] - face0[0], face0[3]])
        cw, ch = max(1, round(crop.shape[1] * s)), max(1, round(crop.shape[0] * s))
        if cw >= w or ch >= h:
            continue
        px, py = int(rng.integers(0, w - cw)), int(rng.integers(0, h - ch))
        rect = np.array([px, py, px + cw, py + ch])
        if any(min(rect[2], r[2]) > max(rect[0], r[0]) and min(rect[3], r[3]) > max(rect[1], r[1]) for r in rects):
            continue
        pasted = _resize(im, (cw, ch)).astype(np.float32) * float(rng.uniform(0.5, 1.3))
        canvas[py:py + ch, px:px + cw] = np.clip(pasted, 0, 255).astype(np.uint8)
        rects.append(rect)
        sx, sy = cw / crop.shape[1], ch / crop.shape[0]
        truths.append(face * np.array([sx, sy, sx, sy]) + np.array([px, py, px, py]))
    return canvas, truths


def _landmarker(detector: str):
    lm = FaceLandmarker(threads=1)
    if detector == "short_range":
        import zipfile

        from ai_edge_litert.interpreter import Interpreter

        with zipfile.ZipFile(lm.task_path) as zf:
            it = Interpreter(model_content=zf.read("face_detector.tflite"), num_threads=1)
        it.allocate_tensors()
        lm.tiled = TiledDetector(it, SHORT_RANGE)
    elif detector != "full_range":
        raise ValueError(f"detector must be full_range or short_range, got {detector!r}")
    return lm


def run_detect_bench(photos: int = 60, negatives: int = 100, sizes_mp: tuple[float, ...] = (1, 4, 12, 24, 50),
                     repeats: int = 3, seed: int = 0, detector: str = "full_range",
                     min_face_px: float = 40.0) -> dict:
    skdata = _skdata()
    lm = _landmarker(detector)
    astronaut = skdata.astronaut()
    backgrounds = [_negative(skdata, n) for n in NEGATIVES]
    rng = np.random.default_rng(seed)
    bands = {b: [0, 0] for b in BANDS}
    extra = confirmed = 0
    t_det = []
    for i in range(photos):
        side = int(round(math.sqrt(float(rng.uniform(0.3, 12.0)) * 1e6 * 4 / 3)))
        image, truths = composite(rng, side, astronaut, backgrounds)
        t0 = time.perf_counter()
        faces = lm(image, min_face_px=min_face_px)
        t_det.append(time.perf_counter() - t0)
        confirmed += sum(f.support is not None for f in faces)
        boxes = np.array([f.detection.box for f in faces]).reshape(-1, 4)
        used = set()
        for t in truths:
            width = t[2] - t[0]
            band = next(b for b in BANDS if b[0] <= width < b[1]) if width >= BANDS[0][0] else None
            hit = False
            if len(boxes):
                overlap = iou(t, boxes)
                j = int(np.argmax(overlap))
                hit = overlap[j] > 0.4
                if hit:
                    used.add(j)
            if band is not None:
                bands[band][0] += int(hit)
                bands[band][1] += 1
        extra += len(faces) - len(used)
    neg_hits = neg_faces = neg_confirmed = 0
    for i in range(negatives):
        img = backgrounds[i % len(backgrounds)]
        s = float(np.exp(rng.uniform(np.log(0.7), np.log(5.0))))
        img = _resize(img, (max(64, round(img.shape[1] * s)), max(64, round(img.shape[0] * s))))
        if rng.random() < 0.5:
            img = np.ascontiguousarray(img[:, ::-1])
        neg_hits += len(lm.detect(img, min_face_px=min_face_px))
        kept = lm(img, min_face_px=min_face_px)
        neg_faces += len(kept)
        neg_confirmed += sum(f.support is not None for f in kept)
    timing = []
    for mp in sizes_mp:
        w = int(round(math.sqrt(mp * 1e6 * 4 / 3)))
        trng = np.random.default_rng(seed + 1)
        size = (w, int(round(w * 3 / 4)))
        image, truths = composite(trng, w, astronaut, backgrounds, size=size)
        while len(truths) < 3:  # a group: several faces to find and landmark
            image, truths = composite(trng, w, astronaut, backgrounds, size=size)
        lm.tiled.windows_run = lm.tiled.windows_skipped = 0
        lm.detect(image, min_face_px=min_face_px)  # warm-up
        windows = lm.tiled.windows_run
        det_s, all_s = [], []
        for _ in range(repeats):
            t0 = time.perf_counter()
            lm.detect(image, min_face_px=min_face_px)
            det_s.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            n_faces = len(lm(image, min_face_px=min_face_px))
            all_s.append(time.perf_counter() - t0)
        timing.append({"megapixels": round(image.shape[0] * image.shape[1] / 1e6, 1),
                       "size": f"{image.shape[1]}x{image.shape[0]}", "windows": windows,
                       "detect_s": float(np.median(det_s)), "detect_landmarks_s": float(np.median(all_s)),
                       "faces": n_faces, "true_faces": len(truths)})
    found = sum(v[0] for v in bands.values())
    total = sum(v[1] for v in bands.values())
    return {
        "detector": detector, "min_face_px": min_face_px, "seed": seed, "photos": photos,
        "recall": found / max(total, 1), "found": found, "true_faces": total,
        "bands": [{"band": _band_name(b), "found": v[0], "faces": v[1],
                   "recall": v[0] / v[1] if v[1] else None} for b, v in bands.items()],
        "extra_detections": extra, "confirmed": confirmed, "photo_median_s": float(np.median(t_det)) if t_det else None,
        "negatives": negatives, "negative_detector_hits": neg_hits, "negative_faces": neg_faces,
        "negative_confirmed": neg_confirmed,
        "false_per_100_photos": 100.0 * neg_faces / max(negatives, 1),
        "timing": timing, "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0, 1),
    }


def rendered_recall(folders, min_face_px: float = 40.0, detector: str = "full_range") -> dict:
    """Detection recall on ``f2l eval render-faces --framing …`` sets (their ``meta/*.json`` hold every
    true face box): by face-width band and by framing. A true face counts when it lies wholly in
    the frame and is at least ``min_face_px`` wide; it is found when a kept face's detection box
    overlaps its box by IoU > 0.3 (the true box runs chin to mid-forehead, BlazeFace's a little
    higher)."""
    import json
    from pathlib import Path

    from PIL import Image

    lm = _landmarker(detector)
    bands = {b: [0, 0] for b in BANDS}
    framings: dict[str, list[int]] = {}
    photos = extra = skipped = confirmed = 0
    misses = []
    for folder in map(Path, folders):
        for meta_path in sorted((folder / "meta").glob("*.json")):
            meta = json.loads(meta_path.read_text())
            faces_all = meta.get("faces", [])
            faces_true = [f for f in faces_all if f["in_frame"] and f["width_px"] >= min_face_px]
            skipped += len(faces_all) - len(faces_true)
            if not faces_true:
                continue
            image = np.asarray(Image.open(folder / "photos" / f"{meta_path.stem}.jpg").convert("RGB"))
            found = lm(image, min_face_px=min_face_px)
            confirmed += sum(f.support is not None for f in found)
            boxes = np.array([f.detection.box for f in found]).reshape(-1, 4)
            used = set()
            photos += 1
            for t in faces_true:
                overlap = iou(np.asarray(t["box"], np.float64), boxes) if len(boxes) else np.zeros(1)
                hit = bool(overlap.max() > 0.3)
                if hit:
                    used.add(int(np.argmax(overlap)))
                else:
                    misses.append({"photo": meta_path.stem, "width_px": t["width_px"],
                                   "yaw_deg": t["pose"]["yaw_deg"]})
                band = next(b for b in BANDS if b[0] <= t["width_px"] < b[1]) if t["width_px"] >= BANDS[0][0] else None
                if band is not None:
                    bands[band][0] += int(hit)
                    bands[band][1] += 1
                fr = framings.setdefault(meta.get("framing", "portrait"), [0, 0])
                fr[0] += int(hit)
                fr[1] += 1
            for j in range(len(boxes)):  # a face not counted (cut by the frame, narrower) is no false detection
                if j not in used and any(iou(np.asarray(t["box"], np.float64), boxes[j:j + 1])[0] > 0.3 for t in faces_all):
                    used.add(j)
            extra += len(found) - len(used)
    found_n = sum(v[0] for v in bands.values())
    total = sum(v[1] for v in bands.values())
    return {"photos": photos, "true_faces": total, "found": found_n, "recall": found_n / max(total, 1),
            "bands": [{"band": _band_name(b), "found": v[0], "faces": v[1], "recall": v[0] / v[1] if v[1] else None}
                      for b, v in bands.items()],
            "framings": {k: {"found": v[0], "faces": v[1]} for k, v in sorted(framings.items())},
            "extra_detections": extra, "confirmed": confirmed, "not_counted": skipped, "misses": misses}


def format_rendered(r: dict) -> str:
    lines = [f"rendered framings: {r['photos']} photos, {r['true_faces']} faces in frame and wide enough "
             f"({r['not_counted']} not counted)", "", "| face width (px) | found / faces | recall |", "|---|---|---|"]
    for b in r["bands"]:
        rec = "—" if b["recall"] is None else f"{100 * b['recall']:.1f}%"
        lines.append(f"| {b['band']} | {b['found']} / {b['faces']} | {rec} |")
    lines.append(f"| all | {r['found']} / {r['true_faces']} | **{100 * r['recall']:.1f}%** |")
    lines.append("\n" + ", ".join(f"{k}: {v['found']} / {v['faces']}" for k, v in r["framings"].items())
                 + f"; {r['extra_detections']} detections that are no face of the scene; "
                 f"{r['confirmed']} faces kept by confirmation")
    return "\n".join(lines)


def _band_name(b) -> str:
    return f"> {b[0]}" if math.isinf(b[1]) else f"{b[0]}-{b[1]}"


def format_table(r: dict) -> str:
    lines = [f"detector {r['detector']}, min face {r['min_face_px']:.0f} px, seed {r['seed']}", "",
             "| face width (px) | found / faces | recall |", "|---|---|---|"]
    for b in r["bands"]:
        rec = "—" if b["recall"] is None else f"{100 * b['recall']:.1f}%"
        lines.append(f"| {b['band']} | {b['found']} / {b['faces']} | {rec} |")
    lines.append(f"| all | {r['found']} / {r['true_faces']} | **{100 * r['recall']:.1f}%** |")
    lines += ["", f"{r['photos']} composites: {r['extra_detections']} detections that are no true face, "
                  f"{r['confirmed']} faces kept by confirmation; "
                  f"median {r['photo_median_s']:.2f} s a photo (detection + landmarks)",
              f"{r['negatives']} face-free photos: {r['negative_detector_hits']} detector hits, "
              f"**{r['negative_faces']} faces after the landmark check and confirmation** "
              f"({r['false_per_100_photos']:.1f} per 100 photos)", "",
              "| photo | MP | windows | detection s | + landmarks s | faces found / true |",
              "|---|---|---|---|---|---|"]
    for t in r["timing"]:
        lines.append(f"| {t['size']} | {t['megapixels']} | {t['windows']} | **{t['detect_s']:.2f}** | "
                     f"{t['detect_landmarks_s']:.2f} | {t['faces']} / {t['true_faces']} |")
    lines.append(f"\npeak memory (RSS) {r['peak_rss_mb']:.0f} MiB; one LiteRT thread")
    return "\n".join(lines)
