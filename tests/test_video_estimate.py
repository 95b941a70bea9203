"""Light from video (f2l.video.head, f2l.video.estimate, f2l video): the head's cached transport
against ray casting, cuts and light changes, interpolation, and end-to-end recovery on clips of
f2l's own renderer (a regression check: the independent path-traced clips are `make eval-video`)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from f2l.cli.app import app
from f2l.face.geometry import NUM_MESH_LANDMARKS
from f2l.lighting.grid import LatLongGrid, direction_from_angles
from f2l.synth.render import pose_matrix
from f2l.transport.visibility import compute_visibility, front_mask, unpack_bits
from f2l.video.changes import ChangeDetector
from f2l.video.estimate import SampleEstimate, VideoOptions, interpolate_params
from f2l.video.head import head_transport
from f2l.video.track import TrackedFace

from tests.video_helpers import focal_35mm, sequence_folder, synth_clip

GRID = LatLongGrid(32, 64)


@pytest.fixture(scope="module")
def table():
    return head_transport(GRID)


def _angle_deg(a, b) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


# -- the head's transport table -------------------------------------------------------------
def test_unturned_head_reads_its_table_exactly_as_ray_casting(table):
    from f2l.face import geometry
    from f2l.face.mesh import canonical_face_mesh

    canon, tri, _ = canonical_face_mesh()
    c = np.asarray(canon, np.float64) - np.asarray(canon, np.float64).mean(0)
    front = np.array([0.0, 0.0, -60.0])
    v, f, vn = geometry.subdivided_mesh(c + front, tri, 2)
    pick = np.arange(0, len(v), 7)
    traced = compute_visibility(v, f, v[pick], vn[pick], GRID)
    read = table.visibility(v[pick], vn[pick], np.eye(3), front)
    assert np.array_equal(read, traced)


def test_a_head_turned_by_whole_columns_reads_its_table_rolled(table):
    """A turn about +Y by k texel columns is a roll of the visibility's columns, exactly."""
    k = 5
    yaw = 2 * math.pi * k / GRID.width
    rot = pose_matrix(math.degrees(yaw), 0.0, 0.0)
    pick = np.arange(0, len(table.vertices), 5)
    centre = np.array([3.0, -2.0, -70.0])
    points = table.vertices[pick] @ rot.T + centre
    normals = table.normals[pick] @ rot.T
    read = unpack_bits(table.visibility(points, normals, rot, centre), GRID.size).reshape(-1, GRID.height, GRID.width)
    own = table.visible[pick].reshape(-1, GRID.height, GRID.width)
    rolled = np.roll(own, -k if _azimuth_shift_sign(rot) < 0 else k, axis=2)
    front = front_mask(normals, GRID).reshape(read.shape)
    assert np.array_equal(read, rolled & front)


def _azimuth_shift_sign(rot) -> float:
    d = rot @ np.array([0.0, 0.0, -1.0])
    return math.atan2(d[0], -d[2])


def test_a_posed_head_reads_its_table_within_a_texel_of_ray_casting(table):
    """Any pose: the table's visibility agrees with rays cast on the posed mesh (the lookups move
    a shadow edge by at most about a texel): ≥ 97% of the bits, uniform-sky shading within 2%."""
    from f2l.face import geometry
    from f2l.transport.visibility import front_cosines

    rot = pose_matrix(28.0, -12.0, 6.0)
    centre = np.array([-4.0, 3.0, -65.0])
    v_cam = table.vertices @ rot.T + centre
    from f2l.face.mesh import canonical_face_mesh

    _, tri, _ = canonical_face_mesh()
    v, f, vn = geometry.subdivided_mesh(v_cam[:NUM_MESH_LANDMARKS], tri, 2)
    pick = np.arange(0, len(v), 9)
    traced = unpack_bits(compute_visibility(v, f, v[pick], vn[pick], GRID), GRID.size).astype(bool)
    read = unpack_bits(table.visibility(v[pick], vn[pick], rot, centre), GRID.size).astype(bool)
    assert (traced == read).mean() >= 0.97
    cos = front_cosines(vn[pick], GRID).reshape(len(pick), -1) * GRID.solid_angles_flat[None]
    e_traced, e_read = (traced * cos).sum(1), (read * cos).sum(1)
    assert np.median(np.abs(e_read - e_traced) / e_traced) < 0.02


# -- changes ------------------------------------------------------------------------------------
def _face(person, box, level, status="ok"):
    x0, y0, x1, y1 = box
    lm = np.zeros((478, 3))
    rng = np.random.default_rng(person)
    lm[:, 0] = rng.uniform(x0 + 5, x1 - 5, 478)
    lm[:, 1] = rng.uniform(y0 + 5, y1 - 5, 478)
    return TrackedFace(0, 0.0, person, lm if status == "ok" else None, 1.0, box, 0.0, 0.0, status, "")


def _frame(backdrop, box, level):
    img = np.empty((180, 320, 3), np.uint8)
    img[:] = backdrop
    x0, y0, x1, y1 = box
    img[y0:y1, x0:x1] = level
    return img


def test_a_new_shot_is_a_cut_and_a_face_that_moves_or_is_covered_is_not():
    det = ChangeDetector(cut_distance=0.5, change_ratio=1.8)
    box, moved = (100, 40, 160, 110), (130, 50, 190, 120)
    assert det.update(_frame((70, 90, 120), box, 180), [_face(0, box, 180)]) is None
    for _ in range(3):
        assert det.update(_frame((70, 90, 120), box, 180), [_face(0, box, 180)]) is None
    assert det.update(_frame((70, 90, 120), moved, 180), [_face(0, moved, 180)]) is None  # the face moved
    assert det.update(_frame((70, 90, 120), moved, 128), [_face(0, moved, 128, "covered")]) is None
    why = det.update(_frame((40, 140, 60), moved, 180), [_face(0, moved, 180)])
    assert why is not None and why.startswith("cut or light")


def test_a_sudden_change_of_the_light_on_a_face_starts_a_segment_and_a_small_one_does_not():
    det = ChangeDetector(cut_distance=0.5, change_ratio=1.8)
    box = (100, 40, 160, 110)
    for _ in range(4):
        assert det.update(_frame((70, 90, 120), box, 200), [_face(0, box, 200)]) is None
    assert det.update(_frame((70, 90, 120), box, 190), [_face(0, box, 190)]) is None  # ~10% darker
    why = det.update(_frame((70, 90, 120), box, 110), [_face(0, box, 110)])  # a cloud: ~3.5x darker
    assert why is not None and why.startswith("light")
    assert det.update(_frame((70, 90, 120), box, 110), [_face(0, box, 110)]) is None  # the new light holds


# -- interpolation ----------------------------------------------------------------------------
def test_the_light_between_two_estimates_moves_the_sun_along_the_great_circle():
    from f2l.estimate.record import _get_model

    model = _get_model("sunsky", GRID)
    lay = model.sun_angles

    def est(time_s, el_deg, az_deg, w):
        p = np.asarray(model.initial_points(), np.float64)[0].copy()
        p[lay.elevation], p[lay.azimuth] = math.radians(el_deg), math.radians(az_deg)
        p[list(model.sun_layout.sky_rgb)] = w
        return SampleEstimate(0, time_s, 0, p, direction_from_angles(math.radians(el_deg), math.radians(az_deg)),
                              0.2, [], [], {}, False, 0.0)

    a, b = est(1.0, 0.0, 0.0, 1.0), est(3.0, 0.0, 90.0, 3.0)
    mid = interpolate_params(model, a, b, 2.0)
    assert math.degrees(mid[lay.azimuth]) == pytest.approx(45.0, abs=1e-9)
    assert mid[lay.elevation] == pytest.approx(0.0, abs=1e-12)
    assert mid[model.sun_layout.sky_rgb[0]] == pytest.approx(2.0)
    assert np.array_equal(interpolate_params(model, a, b, 0.0), interpolate_params(model, a, b, 1.0))
    assert interpolate_params(model, a, b, 9.0)[lay.azimuth] == pytest.approx(math.pi / 2)


def _estimate(segment, el_deg, az_deg, r68=None, samples=("s",)):
    from f2l.estimate.record import _get_model

    model = _get_model("sunsky", GRID)
    p = np.asarray(model.initial_points(), np.float64)[0].copy()
    p[model.sun_angles.elevation], p[model.sun_angles.azimuth] = math.radians(el_deg), math.radians(az_deg)
    return SampleEstimate(0, 0.0, segment, p, direction_from_angles(math.radians(el_deg), math.radians(az_deg)), 0.2,
                          [], [], {}, False, 0.0, cones=None if r68 is None else (r68, 2 * r68, 0.1),
                          samples=list(samples))


def test_two_windows_suns_agree_within_the_smaller_90_percent_cone():
    from f2l.video.sun_share import suns_agree

    a, b = _estimate(0, 30.0, -10.0, 12.0), _estimate(1, 30.0, 13.5, 15.0)  # 20 deg apart
    assert suns_agree((a.sun_direction, a.cones), (b.sun_direction, b.cones))  # r_90 24 and 30
    assert not suns_agree((a.sun_direction, (8.0, 16.0, 0.1)), (b.sun_direction, b.cones))
    assert not suns_agree((a.sun_direction, None), (b.sun_direction, b.cones))
    assert not suns_agree((None, a.cones), (b.sun_direction, b.cones))


def test_the_shared_sun_weighs_each_window_by_its_cone():
    from f2l.video.sun_share import shared_sun_direction

    a, b = _estimate(0, 30.0, -10.0, r68=5.0), _estimate(1, 30.0, 10.0, r68=10.0)
    d = shared_sun_direction([(a.sun_direction, a.cones), (b.sun_direction, b.cones)])
    # weights 1/25 and 1/100: the mean of the two unit vectors with those weights
    expected = a.sun_direction / 25.0 + b.sun_direction / 100.0
    assert np.allclose(d, expected / np.linalg.norm(expected), atol=1e-12)
    assert _angle_deg(d, a.sun_direction) < _angle_deg(d, b.sun_direction)
    # equal cones: halfway on the great circle (a little above 30 deg); a point without cones counts nothing
    mid = shared_sun_direction([(a.sun_direction, (7.0, 14.0)), (b.sun_direction, (7.0, 14.0)),
                                (direction_from_angles(1.4, 0.0), None)])
    halfway = a.sun_direction + b.sun_direction
    assert np.allclose(mid, halfway / np.linalg.norm(halfway), atol=1e-12)
    assert shared_sun_direction([]) is None and shared_sun_direction([(a.sun_direction, None)]) is None


def test_windows_at_an_agreeing_change_share_the_run_s_sun_and_only_the_newest_keeps_its_samples():
    from types import SimpleNamespace

    import torch

    from f2l.estimate.record import _get_model
    from f2l.video.sun_share import SunSharing

    model = _get_model("sunsky", GRID)
    lay = model.sun_angles
    calls = []

    def refit(observations, model_, start, cfg, *, extra_prior, pixel_rc, albedo_group, problems):
        calls.append(start.copy())
        # the prior holds the sun: zero at the start's sun, growing away from it
        moved = start.copy()
        moved[lay.azimuth] += math.radians(3.0)
        assert float(extra_prior(torch.as_tensor(start[None]))) == pytest.approx(0.0, abs=1e-12)
        assert float(extra_prior(torch.as_tensor(moved[None]))) > 0.0
        sun = direction_from_angles(float(start[lay.elevation]), float(start[lay.azimuth]))
        return SimpleNamespace(params=start, sun_direction=sun, ground_albedo=0.3), [SimpleNamespace(data=0.5)]

    def sample():
        return SimpleNamespace(observation=None, pixel_rc=None, person=0, frame=3, problem=object())

    sharing = SunSharing(model, None, VideoOptions(), refit, (ValueError,))
    # segment 0: two windows; segment 1 (a cloud: its sun agrees); segment 2 (a cut to another sun)
    ests = [_estimate(0, 30.0, -20.0, 6.0, [sample()]), _estimate(0, 30.0, -5.0, 6.0, [sample()]),
            _estimate(1, 30.0, 5.0, 6.0, [sample()]), _estimate(2, 50.0, 90.0, 6.0, [sample()])]
    original = [e.sun_direction.copy() for e in ests]
    for k, e in enumerate(ests):
        sharing.add(e, ests[k - 1] if k else None)
        assert all(not x.samples for x in ests[:k]) and e.samples  # only the newest keeps its samples
    assert len(calls) == 2 and sharing.refits == 2  # the windows on either side of the cloud, not of the cut
    shared = original[1] + original[2]
    for e in ests[1:3]:
        assert np.allclose(e.sun_direction, shared / np.linalg.norm(shared), atol=1e-9)
        assert e.ground_albedo == 0.3 and e.residual == {(3, 0): 0.5} and e.cones == (6.0, 12.0, 0.1)
    assert np.array_equal(ests[0].sun_direction, original[0]) and np.array_equal(ests[3].sun_direction, original[3])

    def fails(*args, **kwargs):
        raise ValueError("no")

    a, b = _estimate(0, 30.0, -5.0, 6.0, [sample()]), _estimate(1, 30.0, 5.0, 6.0, [sample()])
    sharing = SunSharing(model, None, VideoOptions(), fails, (ValueError,))
    sharing.add(a, None)
    sharing.add(b, a)
    assert sharing.refits == 0 and np.array_equal(b.sun_direction, direction_from_angles(math.radians(30.0),
                                                                                         math.radians(5.0)))


# -- end to end -------------------------------------------------------------------------------
SUNS = [(35.0, 60.0), (20.0, -80.0)]


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """A render-faces --sequence-like folder with one synthetic two-shot clip."""
    return sequence_folder(tmp_path_factory.mktemp("seq"), SUNS, renders=4, hold=3, yaw_range_deg=15.0)


@pytest.fixture(scope="module")
def clip(sequence):
    truth = json.loads((sequence / "truth" / "clip-s0-00000-cut.json").read_text())
    per_frame = [{"segment": f["segment"], "sun": np.asarray(f["sun_direction"])} for f in truth["per_frame"]]
    return sequence / "clips" / "clip-s0-00000-cut.mp4", per_frame


@pytest.fixture(autouse=True)
def _cache(tmp_path_factory, monkeypatch):
    monkeypatch.setenv("F2L_CACHE_DIR", str(tmp_path_factory.getbasetemp() / "f2l-cache"))


def _run(clip_path: Path, out: Path, *extra):
    return CliRunner().invoke(app, ["video", str(clip_path), "-m", "sunsky", "--out", str(out), "--every", "4",
                                    "--sample-every", "3", "--focal-35mm", f"{focal_35mm(160):.4f}", *extra])


def test_a_clip_gives_a_light_per_frame_that_finds_each_shots_sun(clip, tmp_path):
    path, truth = clip
    res = _run(path, tmp_path / "out", "--json")
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output)
    assert [s["first_frame"] for s in summary["segments"]] == [0, 12]
    assert summary["segments"][1]["why"].startswith("cut or light")
    rows = pq.read_table(tmp_path / "out" / "frames.parquet").to_pylist()
    assert [r["frame"] for r in rows] == list(range(24))
    for r in rows:  # the window's sun cones on every frame (full joint estimates), ordered
        assert 0.0 < r["sun_cone68_deg"] < r["sun_cone90_deg"] <= 180.0 and r["predicted_mae_s"] >= 0.0
    for r in rows:
        assert r["status"] == "ok" and r["segment"] == truth[r["frame"]]["segment"]
        assert _angle_deg(r["sun_direction"], truth[r["frame"]]["sun"]) < 15.0, r
        assert all(w // 12 == r["frame"] // 12 for w in r["window"])  # no frame lit from another shot
    sun = np.array([r["sun_direction"] for r in rows])
    steps = [_angle_deg(sun[i], sun[i + 1]) for i in range(23) if i != 11]
    assert max(steps) < 5.0
    probes = sorted((tmp_path / "out" / "probes" / "sunsky").glob("*.exr"))
    assert [p.name for p in probes] == [f"frame-{i:06d}.exr" for i in range(0, 24, 4)]
    from f2l.io.probe_io import read_hdr_image

    probe = read_hdr_image(probes[0])
    assert probe.shape == (64, 128, 3) and np.isfinite(probe).all()
    cap = cv2.VideoCapture(str(tmp_path / "out" / "preview.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 24
    cap.release()
    assert (tmp_path / "out" / "sun_track.png").stat().st_size > 0
    res = CliRunner().invoke(app, ["report", str(tmp_path / "out")])
    assert res.exit_code == 0, res.output
    html = (tmp_path / "out" / "report.html").read_text()
    assert 'id="clip"' in html and "sun_track.png" in html and "cut or light" in html


def test_a_segment_is_sampled_densely_until_its_first_light_then_every_sample_every(clip, tmp_path):
    """cold_faces=2, sample_every=3: the first light waits for samples 3 frames apart; until it,
    every frame is sampled (cold_sample_every=1), after it every 3rd; each shot starts afresh."""
    from f2l.video.run import estimate_clip

    path, truth = clip
    options = VideoOptions(model="sunsky", sample_every=3, cold_sample_every=1, cold_faces=2,
                           focal_35mm_mm=focal_35mm(160))
    estimate_clip(path, tmp_path / "out", options, every=0, preview=False)
    rows = pq.read_table(tmp_path / "out" / "frames.parquet").to_pylist()
    assert [r["frame"] for r in rows if r["sample"]] == [0, 1, 2, 3, 6, 9, 12, 13, 14, 15, 18, 21]
    for r in rows:
        assert r["status"] == "ok" and _angle_deg(r["sun_direction"], truth[r["frame"]]["sun"]) < 15.0, r
    clip_json = json.loads((tmp_path / "out" / "clip.json").read_text())
    first = [e for e in clip_json["estimates"] if e["cold"]]
    assert [e["frame"] for e in first] == [3, 15]  # fired once the samples spanned 3 frames
    assert set(first[0]["window"]) <= {0, 1, 2, 3} and set(first[1]["window"]) <= {12, 13, 14, 15}
    with pytest.raises(ValueError, match="cold_sample_every"):
        VideoOptions(cold_sample_every=0)


def test_frames_where_the_face_is_covered_carry_a_status_and_the_rest_keep_their_light(clip, tmp_path):
    path, truth = clip
    covered = tmp_path / "covered.mp4"
    cap = cv2.VideoCapture(str(path))
    writer = cv2.VideoWriter(str(covered), cv2.VideoWriter_fourcc(*"mp4v"), 24.0, (160, 160))
    for i in range(24):
        ok, bgr = cap.read()
        assert ok
        if i in (4, 5, 6):
            bgr[40:130, 35:125] = 128  # a grey card over the face
        writer.write(bgr)
    writer.release()
    cap.release()
    res = _run(covered, tmp_path / "out", "--json", "--no-preview")
    assert res.exit_code == 0, res.output
    assert [s["first_frame"] for s in json.loads(res.output)["segments"]] == [0, 12]
    rows = {r["frame"]: r for r in pq.read_table(tmp_path / "out" / "frames.parquet").to_pylist()}
    for i, r in rows.items():
        if i in (4, 5, 6):
            assert r["status"] in ("covered", "lost") and not r["sample"]
        else:
            assert r["status"] == "ok"
        assert _angle_deg(r["sun_direction"], truth[i]["sun"]) < 15.0


def test_a_file_that_is_not_a_video_fails_with_its_name(tmp_path):
    bad = tmp_path / "notes.mp4"
    bad.write_text("not a video")
    res = _run(bad, tmp_path / "out")
    assert res.exit_code == 1
    assert "notes.mp4" in res.output


def test_estimate_given_a_clip_points_to_f2l_video(clip, tmp_path):
    path, _ = clip
    res = CliRunner().invoke(app, ["estimate", str(path), "-m", "sunsky", "--out", str(tmp_path / "est")])
    assert res.exit_code == 2
    assert "f2l video" in res.output and path.name in res.output


def test_eval_video_scores_a_clip_against_its_truth_and_each_frame_alone(sequence, tmp_path):
    res = CliRunner().invoke(app, ["eval", "video", str(sequence), "--out", str(tmp_path / "ev"), "--json",
                                   "--sample-every", "3", "--alone-every", "6", "--metrics-every", "12"])
    assert res.exit_code == 0, res.output
    (row,) = json.loads(res.output)
    assert row["clip"] == "clip-s0-00000-cut" and row["part"] == "tune" and row["scored_frames"] == 24
    assert row["change_found"] is True and row["false_changes"] == 0 and row["settle_s"] is not None
    assert row["sun_ang_video"] < 15.0 and row["alone_frames"] >= 3 and row["sun_ang_alone"] is not None
    assert row["jitter_rms_deg"] is not None and row["jitter_rms_deg"] < 2.0
    assert row["mae_s_video"] is not None and row["frames_per_s"] > 0
    assert 0.0 <= row["in_cone68"] <= row["in_cone90"] <= 1.0  # each window's cones, scored
    assert "clip-s0-00000-cut" in (tmp_path / "ev" / "video.md").read_text()


def test_bench_video_times_a_clip_in_a_fresh_process(clip, tmp_path):
    from f2l.dev.bench_video import bench_video, ping_pong, table

    path, _ = clip
    longer, order = ping_pong(path, 2, tmp_path)
    assert len(order) == 48 and order[23] == 23 and order[24] == 23 and order[47] == 0
    (row,) = bench_video([path], extra=["--focal-35mm", f"{focal_35mm(160):.4f}"])
    assert "error" not in row, row
    assert row["frames"] == 24 and row["frames_per_s"] > 0 and row["startup_s"] >= 0 and row["sun_ang"] < 15.0
    assert "frames/s" in table([row])
