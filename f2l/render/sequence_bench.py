"""What a clip's frame costs, and what its shortcuts give away (``docs/experiments/video_clips.md``).

``python -m f2l.render.sequence_bench [--image-px 1280] [--spp 4] [--reference-spp 64]`` on one
shot of clip 0 (seed 0), all in one process so that the ratios hold on a loaded machine:

- ``photo_path``: the photos' renderer (:func:`f2l.render.scene.render_head`: the whole frame, an
  AOV pass for depth, a scene built from PLY files) at ``spp``;
- ``sequence``: a clip's frame (:meth:`f2l.render.sequence._Shot.render`: the head posed by scene
  parameters, its window at ``spp`` and the torso's at ``spp // 2``, denoised, over the shot's
  background), and its parts (posing, windows);
- noise: the relative RMS difference, over the face's pixels, between the head's window at ``spp``
  (raw and denoised) and at ``reference_spp`` (itself noisy: its own difference from its denoised
  self is printed as the floor);
- codec: PSNR (dB) of ``frames`` frames after OpenCV's mp4v round trip, against the 8-bit frames
  handed to it, and the mean signed error per channel (decoded − written, 8-bit codes).

Wall seconds and process CPU seconds (all threads) are both given: CPU / 2 estimates a frame's
wall time on two idle cores.

``--sheet DIR --figure PATH``: instead, a contact sheet of a ``render-faces --sequence`` folder
(:func:`contact_sheet`).
"""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path

import numpy as np

from f2l.render.dataset import RenderOptions


def _timed(fn):
    t, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, {"wall_s": round(time.perf_counter() - t, 3), "cpu_s": round(time.process_time() - cpu, 3)}


def bench(image_px: int = 1280, spp: int = 4, reference_spp: int = 64, frames: int = 6, seed: int = 0,
          index: int = 0) -> dict:
    """The figures of the module docstring, as a JSON-ready dict."""
    import cv2

    from f2l.render import sequence as seq
    from f2l.render.scene import render_head, sensor_dict

    options = RenderOptions(image_px=image_px, spp=spp)
    spec = seq.draw_clip(seed, index, options, seq.SequenceOptions(frames=max(frames, 2), clip_kind="static"))
    shot, setup = _timed(lambda: seq._Shot(spec, spec["segments"][0], options, {}))
    pose = seq.head_pose(spec["motion"], 0, spec["frames"])
    vertices, posing = _timed(lambda: shot.pose(pose))
    _, frame = _timed(lambda: shot.render(vertices, seed=1))
    from f2l.render.heads import Head

    posed = Head(vertices, shot.head.faces, shot.head.albedo, shot.head.part,
                 seq.pose_vertices(shot.head.vertices, shot.head.normals, shot.weights, pose, shot.offset_cm)[1])
    _, photo = _timed(lambda: render_head(posed, shot.lighting, shot.settings))

    mi = shot.mi
    window = shot._window(vertices[shot.weights >= seq.HEAD_WEIGHT])
    sensor = mi.load_dict(sensor_dict(mi, shot.settings, "rgb", window))

    def head_window(n: int, s: int) -> np.ndarray:
        return np.clip(np.array(mi.render(shot.scene, sensor=sensor, seed=s, spp=n)), 0.0, None)

    reference, reference_time = _timed(lambda: head_window(reference_spp, 7))
    raw, window_time = _timed(lambda: head_window(spp, 3))
    x0, y0, x1, y1 = window
    face = shot.face_pixels(vertices, shot.face_box(vertices))[y0:y1, x0:x1]

    def rel_rms(image: np.ndarray, ref: np.ndarray) -> float:
        return round(float(np.sqrt(np.mean((image[face] - ref[face]) ** 2)) / np.mean(ref[face])), 4)

    noise = {"raw": rel_rms(raw, reference), "denoised": rel_rms(seq.denoise(raw), reference),
             "reference_floor": rel_rms(seq.denoise(reference), reference)}

    exposure = seq._exposure(shot.render(vertices, seed=2), shot.face_pixels(vertices, shot.face_box(vertices)),
                             spec["segments"][0]["noise"]["exposure_percentile"])
    written = []
    with tempfile.TemporaryDirectory() as tmp:
        writer = seq._VideoWriter(Path(tmp) / "bench.mp4", spec["fps"], seq.frame_size(image_px))
        for f in range(frames):
            v = shot.pose(seq.head_pose(spec["motion"], f, spec["frames"]))
            rgb = seq._sensor(shot.render(v, seed=10 + f), exposure, spec["segments"][0]["noise"],
                              np.random.default_rng(f))
            written.append(rgb)
            writer.write(rgb)
        writer.close(keep=True)
        cap = cv2.VideoCapture(str(Path(tmp) / "bench.mp4"))
        psnr, bias = [], []
        for rgb in written:
            ok, bgr = cap.read()
            psnr.append(float(cv2.PSNR(np.ascontiguousarray(bgr[..., ::-1]), rgb)) if ok else float("nan"))
            if ok:
                bias.append((bgr[..., ::-1].astype(np.float64) - rgb).mean(axis=(0, 1)))
        cap.release()
    return {"image": list(seq.frame_size(image_px)), "spp": spp, "clip": spec["clip_id"],
            "head_width_fraction": spec["segments"][0]["camera"]["head_width_fraction"],
            "head_window_px": [int(x1 - x0), int(y1 - y0)],
            "shot_setup": setup, "pose_and_bvh": posing, "sequence_frame": frame, "photo_path_frame": photo,
            "head_window_at_spp": window_time, f"head_window_at_{reference_spp}_spp": reference_time,
            "face_noise_rel_rms": noise, "codec": seq.CODEC,
            "codec_psnr_db": {"mean": round(float(np.mean(psnr)), 2), "min": round(float(np.min(psnr)), 2)},
            "codec_mean_error_rgb_codes": [round(float(c), 2) for c in np.mean(bias, axis=0)]}


def contact_sheet(render_dir: Path, figure: Path, clips: int = 3, width_px: int = 320) -> Path:
    """A JPEG of the first ``clips`` clips of a ``render-faces --sequence`` folder: per clip (a row)
    its first frame, the frames either side of its change (or the middle two) and its last."""
    import cv2

    index = json.loads((Path(render_dir) / "clips.json").read_text())
    rows = []
    for clip in [c for c in index["clips"] if c["status"] in ("ok", "exists")][:clips]:
        truth = json.loads((Path(render_dir) / clip["truth"]).read_text())
        n, change = truth["frames"], truth["change_frame"] or truth["frames"] // 2
        cap = cv2.VideoCapture(str(Path(render_dir) / truth["video"]))
        decoded = []
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            decoded.append(frame)
        cap.release()
        tiles = []
        for f in (0, change - 1, change, n - 1):
            tile = cv2.resize(decoded[f], (width_px, width_px * truth["height_px"] // truth["width_px"]),
                              interpolation=cv2.INTER_AREA)
            cv2.putText(tile, f"{truth['kind']} f{f}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 2)
            cv2.putText(tile, f"{truth['kind']} f{f}", (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1)
            tiles.append(tile)
        rows.append(np.concatenate(tiles, axis=1))
    from f2l.io.atomic import atomic_path

    with atomic_path(figure) as tmp:
        ok, data = cv2.imencode(".jpg", np.concatenate(rows, axis=0), [cv2.IMWRITE_JPEG_QUALITY, 85])
        Path(tmp).write_bytes(data.tobytes())
    return Path(figure)


def main(argv=None) -> None:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--image-px", type=int, default=1280)
    parser.add_argument("--spp", type=int, default=4)
    parser.add_argument("--reference-spp", type=int, default=64)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--index", type=int, default=0)
    parser.add_argument("--sheet", type=Path, help="Instead: a contact sheet of this render-faces --sequence folder.")
    parser.add_argument("--figure", type=Path, default=Path("video_clips.jpg"), help="Where --sheet writes it.")
    args = parser.parse_args(argv)
    if args.sheet is not None:
        print(contact_sheet(args.sheet, args.figure))
        return
    print(json.dumps(bench(args.image_px, args.spp, args.reference_spp, args.frames, index=args.index), indent=1))


if __name__ == "__main__":
    main()
