"""`f2l eval render-faces --sequence`: path-traced clips of a head turning and nodding under one light,
a cloud over the sun, or a cut (f2l.render.sequence)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from f2l.render.dataset import RenderOptions

FRAMES, LONG_PX = 6, 160


@pytest.fixture(scope="module")
def clips(tmp_path_factory):
    """One static, one cloud and one cut clip: 6 frames, 160 × 90, 1 spp."""
    pytest.importorskip("mitsuba")
    pytest.importorskip("anny")
    from f2l.render.sequence import SequenceOptions, render_clips

    out = tmp_path_factory.mktemp("clips")
    summary = render_clips(out, 3, seed=2, options=RenderOptions(image_px=LONG_PX, spp=1),
                           sequence=SequenceOptions(frames=FRAMES, clip_kind="mixed"), progress=False)
    assert summary["ok"] == 3, summary
    index = json.loads((out / "clips.json").read_text())
    truths = {c["kind"]: json.loads((out / c["truth"]).read_text()) for c in index["clips"]}
    return out, truths


def _frames(path) -> tuple[list[np.ndarray], float]:
    import cv2

    cap = cv2.VideoCapture(str(path))
    fps = cap.get(cv2.CAP_PROP_FPS)
    frames = []
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames.append(frame[..., ::-1].astype(np.float64))
    cap.release()
    return frames, fps


def test_draws_are_deterministic_and_kinds_cycle():
    from f2l.render.sequence import SequenceOptions, draw_clip

    seq = SequenceOptions(frames=48)
    kinds = [draw_clip(0, i, sequence=seq)["kind"] for i in range(6)]
    assert kinds == ["static", "cloud", "cut"] * 2
    for i in range(12):
        spec = draw_clip(1, i, sequence=seq)
        assert spec == draw_clip(1, i, sequence=seq)
        assert 35 <= spec["motion"]["yaw_amplitude_deg"] <= 45 and 10 <= spec["motion"]["pitch_amplitude_deg"] <= 15
        if spec["kind"] == "cloud":  # a cloud dims a sky's sun, the sky and the shot stay
            a, b = spec["segments"]
            assert a["lighting"]["source"] == "sunsky" and b["lighting"] == a["lighting"]
            assert abs(a["lighting"]["sun_azimuth_deg"]) >= 90.0  # in front of the face, which it lights
            assert a["sun_power_scale"] == 1.0 and 0.1 <= b["sun_power_scale"] <= 0.2 and spec["change_frame"] == 24
        elif spec["kind"] == "cut":
            a, b = spec["segments"]
            assert a["lighting"] != b["lighting"] and spec["change_frame"] == 24
            if a["lighting"]["source"] == b["lighting"]["source"] == "sunsky":
                gap = (b["lighting"]["sun_azimuth_deg"] - a["lighting"]["sun_azimuth_deg"] + 180) % 360 - 180
                assert abs(gap) >= 40.0 - 1e-6
        else:
            assert len(spec["segments"]) == 1 and spec["change_frame"] is None
    with pytest.raises(ValueError, match="clip kind"):
        SequenceOptions(clip_kind="rain")


def test_only_the_head_turns_about_its_pivot():
    from f2l.render.sequence import PIVOT_CM, pose_vertices, twist_weights

    points = np.array([[0.0, 0.0, 0.0], [0.0, 8.0, -5.0], [18.0, -24.0, -4.0], [-15.0, -28.0, 2.0]])
    w = twist_weights(points)
    assert w.tolist() == [1.0, 1.0, 0.0, 0.0]  # eyes and crown follow; shoulders stay
    normals = np.tile([0.0, 0.0, 1.0], (4, 1))
    v, n = pose_vertices(points, normals, w, (30.0, 0.0, 0.0), [1.0, 2.0, 3.0])
    # yaw 30° about the pivot: the eyes swing about a vertical axis through it, facing toward +X
    rel = points[0] - PIVOT_CM
    expected = PIVOT_CM + [rel[2] * np.sin(np.radians(30)), rel[1], rel[2] * np.cos(np.radians(30))] + [1, 2, 3]
    np.testing.assert_allclose(v[0], expected, atol=1e-9)
    np.testing.assert_allclose(n[0], [np.sin(np.radians(30)), 0, np.cos(np.radians(30))], atol=1e-12)
    np.testing.assert_allclose(v[2:], points[2:] + [1, 2, 3])
    np.testing.assert_allclose(n[2:], normals[2:])


def test_denoise_halves_noise_and_keeps_a_hard_edge():
    from f2l.render.sequence import denoise

    rng = np.random.default_rng(0)
    clean = np.full((64, 64, 3), 0.2)
    clean[:, 32:] = 1.0  # a hard shadow edge
    noisy = clean * (1 + 0.15 * rng.standard_normal(clean.shape))
    out = denoise(np.clip(noisy, 0, None))
    inner = (slice(4, 60), slice(4, 28))
    assert np.std(out[inner] / 0.2) < 0.5 * np.std(noisy[inner] / 0.2)
    assert abs(out[:, 34:].mean() - 1.0) < 0.03 and abs(out[:, :30].mean() - 0.2) < 0.01  # the edge stays sharp


def test_a_failing_clip_does_not_stop_the_others(tmp_path, monkeypatch):
    from f2l.render import sequence

    def fake(spec, options, out):
        if spec["index"] == 1:
            raise RuntimeError("the face is not in the frame")
        (out / "truth").mkdir(parents=True, exist_ok=True)
        (out / "truth" / f"{spec['clip_id']}.json").write_text("{}")
        return {"timings_s": {"per_frame_mean": 0.5, "per_frame_cpu_mean": 0.9}}

    monkeypatch.setattr(sequence, "render_clip", fake)
    summary = sequence.render_clips(tmp_path, 3, seed=0, progress=False)
    assert summary["ok"] == 2 and list(summary["errors"]) == ["clip-s0-00001-cloud"]
    again = sequence.render_clips(tmp_path, 3, seed=0, progress=False)
    assert again["skipped_existing"] == 2 and list(again["errors"]) == ["clip-s0-00001-cloud"]


def test_the_video_is_written_atomically(tmp_path):
    from f2l.render.sequence import _VideoWriter

    stale = tmp_path / ".clip-a.999.tmp.mp4"
    stale.write_bytes(b"left by a killed run")
    writer = _VideoWriter(tmp_path / "clip-a.mp4", 24.0, (64, 36))
    writer.write(np.zeros((36, 64, 3), np.uint8))
    assert not stale.exists() and not (tmp_path / "clip-a.mp4").exists()
    writer.close(keep=False)  # a failed clip leaves nothing
    assert list(tmp_path.iterdir()) == []
    writer = _VideoWriter(tmp_path / "clip-a.mp4", 24.0, (64, 36))
    for _ in range(3):
        writer.write(np.full((36, 64, 3), 128, np.uint8))
    writer.close(keep=True)
    assert [p.name for p in tmp_path.iterdir()] == ["clip-a.mp4"]
    frames, fps = _frames(tmp_path / "clip-a.mp4")
    # OpenCV's mp4v round trip darkens flat grey by ~4 codes (docs/experiments/video_clips.md)
    assert len(frames) == 3 and fps == pytest.approx(24.0) and abs(frames[1].mean() - 128) < 6


def test_clips_read_back_with_their_frame_count_size_and_fps(clips):
    out, truths = clips
    assert sorted(truths) == ["cloud", "cut", "static"]
    for kind, truth in truths.items():
        frames, fps = _frames(out / truth["video"])
        assert len(frames) == truth["frames"] == FRAMES and fps == pytest.approx(24.0)
        assert frames[0].shape == (truth["height_px"], truth["width_px"], 3) == (90, 160, 3)
        assert [f["frame"] for f in truth["per_frame"]] == list(range(FRAMES))
        assert all((out / s["probe"]).is_file() for s in truth["segments"])


def test_the_head_follows_its_planned_path_inside_its_face_box(clips):
    from f2l.render.sequence import head_pose, pose_vertices

    out, truths = clips
    for truth in truths.values():
        motion = truth["draw"]["motion"]
        for f in truth["per_frame"]:
            yaw, pitch, roll = head_pose(motion, f["frame"], truth["frames"])
            pose = (f["head_yaw_deg"], f["head_pitch_deg"], f["head_roll_deg"])
            assert pose == pytest.approx((yaw, pitch, roll), abs=1e-3)
            seg = truth["segments"][f["segment"]]
            cam = seg["camera"]
            width_cm = 16.0 / cam["head_width_fraction"]
            offset = [cam["shift_fraction"] * width_cm,
                      (0.5 - cam["eyes_row_fraction"]) * width_cm * truth["height_px"] / truth["width_px"], 0.0]
            # the eyes' midpoint and a point on the nose, posed and projected by a pinhole
            rest = np.array([[0.0, 0.0, 0.0], [0.0, -4.0, 2.0]])
            v, _ = pose_vertices(rest, np.tile([0, 0, 1.0], (2, 1)), np.ones(2), (yaw, pitch, roll), offset)
            z = seg["camera_distance_cm"] - v[:, 2]
            cols = truth["width_px"] / 2 + truth["focal_px"] * v[:, 0] / z
            rows = truth["height_px"] / 2 - truth["focal_px"] * v[:, 1] / z
            x0, y0, x1, y1 = f["face_box"]
            assert ((cols > x0) & (cols < x1) & (rows > y0) & (rows < y1)).all(), (f, cols, rows)
            assert 0.1 * truth["width_px"] < x1 - x0 < 0.35 * truth["width_px"]  # a vlog's face


def test_the_true_sun_is_the_probes_brightest_texel(clips):
    from f2l.io.exr import read_exr
    from f2l.lighting.grid import LatLongGrid
    from f2l.lighting.sun import brightest_direction

    out, truths = clips
    grid = LatLongGrid(128, 256)
    texel_deg = 180.0 / 128
    for truth in truths.values():
        for seg in truth["segments"]:
            _, direction = brightest_direction(read_exr(out / seg["probe"]).astype(np.float64), grid)
            angle = np.degrees(np.arccos(np.clip(np.dot(direction, seg["sun_direction"]), -1, 1)))
            assert angle <= 2 * texel_deg, (truth["clip_id"], seg)
            for f in truth["per_frame"][seg["first_frame"]: seg["last_frame"] + 1]:
                assert f["segment"] == seg["segment"] and f["sun_direction"] == seg["sun_direction"]


def test_a_cut_changes_the_shot_and_a_cloud_dims_the_sun_at_the_change_frame(clips):
    from f2l.io.exr import read_exr
    from f2l.lighting.grid import LatLongGrid

    out, truths = clips
    static, cut, cloud = truths["static"], truths["cut"], truths["cloud"]
    assert static["change_frame"] is None and len(static["segments"]) == 1
    for truth in (cut, cloud):
        change = truth["change_frame"]
        assert change == FRAMES // 2
        assert [f["segment"] for f in truth["per_frame"]] == [0] * change + [1] * (FRAMES - change)
        assert truth["segments"][0]["last_frame"] == change - 1 and truth["segments"][1]["first_frame"] == change
    a, b = cut["segments"]
    assert a["lighting"] != b["lighting"]
    assert not np.allclose(read_exr(out / a["probe"]), read_exr(out / b["probe"]))
    frames, _ = _frames(out / cut["video"])
    jumps = [np.abs(frames[i + 1] - frames[i]).mean() for i in range(FRAMES - 1)]
    assert int(np.argmax(jumps)) == cut["change_frame"] - 1  # the biggest change is the cut
    # the cloud: the sun's power scale drops at the change frame; same shot, same exposure
    scales = [f["sun_power_scale"] for f in cloud["per_frame"]]
    change = cloud["change_frame"]
    assert scales[:change] == [1.0] * change and all(0.1 <= s <= 0.2 for s in scales[change:])
    a, b = cloud["segments"]
    assert a["exposure"] == b["exposure"] and a["sun_direction"] == b["sun_direction"]
    grid = LatLongGrid(128, 256)
    row, col = grid.direction_to_texel(np.asarray(a["sun_direction"]))
    sun0, sun1 = (read_exr(out / s["probe"])[int(row), int(col)].astype(np.float64) for s in (a, b))
    np.testing.assert_allclose(sun1 / sun0, b["sun_power_scale"], rtol=0.02)  # the sun texel is nearly all sun


def test_a_rerun_through_the_cli_skips_done_clips(clips):
    from typer.testing import CliRunner

    from f2l.cli import app

    out, truths = clips
    before = {k: (out / t["video"]).stat().st_mtime_ns for k, t in truths.items()}
    res = CliRunner().invoke(app, ["eval", "render-faces", "--sequence", "--n", "3", "--seed", "2", "--frames",
                                   str(FRAMES), "--image-px", str(LONG_PX), "--spp", "1", "--out", str(out), "--json"])
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output.strip().splitlines()[-1])
    assert summary["skipped_existing"] == 3 and summary["ok"] == 0
    assert {k: (out / t["video"]).stat().st_mtime_ns for k, t in truths.items()} == before
    bad = CliRunner().invoke(app, ["eval", "render-faces", "--sequence", "--framing", "group", "--out", str(out)])
    assert bad.exit_code != 0 and "--sequence" in bad.output


@pytest.mark.slow
def test_the_frame_bench_runs_and_denoising_lowers_the_noise():
    """`python -m f2l.render.sequence_bench` on a tiny frame (the doc's figures are at 1280 × 720)."""
    pytest.importorskip("mitsuba")
    pytest.importorskip("anny")
    from f2l.render.sequence_bench import bench

    result = bench(image_px=160, spp=1, reference_spp=8, frames=2)
    assert result["image"] == [160, 90] and result["codec"] == "mp4v"
    assert result["face_noise_rel_rms"]["denoised"] < result["face_noise_rel_rms"]["raw"]
    assert result["codec_psnr_db"]["min"] > 25.0
    assert result["sequence_frame"]["cpu_s"] < result["photo_path_frame"]["cpu_s"]
