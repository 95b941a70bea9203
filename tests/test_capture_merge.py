"""RAW-domain bracket merge on synthetic DNG brackets (f2l.capture.merge)."""

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

from f2l.capture.dng import synthetic_sky_scene, write_bracket
from f2l.capture.merge import BracketError, merge_bracket, raw_frame
from f2l.dev.bench_merge import bench_merge
from f2l.io.raw_meta import XYZ_TO_REC709, RawError, bayer_mosaic, demosaic_bilinear, read_raw

EXPOSURES_S = [1 / 4000 * 4**k for k in range(7)]  # 2 EV apart at f/8, ISO 100: 1/4000 s ... 1.024 s
E_MIN = EXPOSURES_S[0] / 64  # exposure factor t * (ISO / 100) / N^2 of the shortest frame


def _ideal(scene):
    """What a noise-free merge must give: the bilinear demosaic of the scene's mosaic."""
    return demosaic_bilinear(bayer_mosaic(scene.astype(np.float32), "RGGB"), "RGGB")


def _median_rel_error(result, scene):
    ok = ~result.saturated
    return float(np.median((np.abs(result.rgb - _ideal(scene)) / _ideal(scene))[ok]))


@pytest.fixture(scope="module")
def scene():
    return synthetic_sky_scene(96, 128, seed=0)


@pytest.fixture(scope="module")
def bracket(scene, tmp_path_factory):
    return write_bracket(tmp_path_factory.mktemp("bracket"), scene, EXPOSURES_S, seed=3)


@pytest.fixture(scope="module")
def merged(bracket):
    return merge_bracket(bracket)


def test_merge_recovers_hdr_scene(scene, merged):
    ok = ~merged.saturated
    assert merged.rgb.dtype == np.float32 and merged.rgb.shape == (96, 128, 3)
    assert scene[ok].max() / scene[ok].min() >= 1e5  # unclipped dynamic range of the test scene
    err = _median_rel_error(merged, scene)
    assert err <= 0.02
    mosaic_err = np.abs(merged.mosaic - bayer_mosaic(scene, "RGGB")) / bayer_mosaic(scene, "RGGB")
    assert np.median(mosaic_err[ok]) <= 0.02
    ideal = _ideal(scene)
    rel = np.abs(merged.rgb - ideal) / ideal
    assert ideal[ok].max() / ideal[ok].min() >= 1e5  # the recovered range spans five decades
    green = ideal[..., 1]
    darkest, brightest = ok & (green <= np.percentile(green[ok], 1)), ok & (green >= np.percentile(green[ok], 99))
    assert np.median(rel[darkest]) <= 0.06 and np.median(rel[brightest]) <= 0.02  # both ends of the range
    assert merged.status == "ok" and merged.colour_space == "camera" and merged.scale == 1.0
    assert np.all(np.isfinite(merged.rgb)) and merged.rgb.min() >= 0
    infos = merged.frames
    assert [f.exposure_s for f in infos] == pytest.approx(EXPOSURES_S)
    assert [f.ev100 for f in infos] == pytest.approx([-np.log2(t / 64) for t in EXPOSURES_S])
    assert not any(f.moved or f.aligned for f in infos)
    assert infos[3].status == "reference" and merged.reference.endswith("frame_03.dng")


def test_frames_weigh_where_unclipped_and_the_longest_one_dominates(bracket, merged):
    """Recomputed from the DNGs' own DN with the documented rules: a frame weighs a 2x2 quad unless
    a sample is at or above black + 0.95 (white - black) or (not the longest frame) the quad's mean
    signal is under 4 read-noise sigmas (8 DN); its inverse-variance weight grows ~e^2 / e, 4x per
    2 EV step, so the longest frame that weighs a quad dominates it. Quads no frame weighs (the
    sun) dominate nowhere, and the flagged `saturated` pixels cover all of them."""
    used, dominant = [], np.full((48, 64), -1)
    for i, path in enumerate(bracket):  # shortest exposure first
        meta, dn = read_raw(path)
        quads = dn.reshape(48, 2, 64, 2).astype(np.float64)
        black = np.reshape(meta.black_levels, (1, 2, 1, 2))
        clipped = (quads >= black + 0.95 * (meta.white_level - black)).any(axis=(1, 3))
        dark = (quads - black).mean(axis=(1, 3)) < 8.0
        weighs = ~clipped if i == len(bracket) - 1 else ~clipped & ~dark
        used.append(weighs.mean())
        dominant[weighs] = i
    assert [f.used_fraction for f in merged.frames] == pytest.approx(used, abs=0)
    want = [float((dominant == i).mean()) for i in range(len(bracket))]
    assert [f.dominant_fraction for f in merged.frames] == pytest.approx(want, abs=0)
    nobody = dominant == -1
    assert 0 < nobody.mean() < 0.05
    assert merged.saturated.reshape(48, 2, 64, 2).all(axis=(1, 3))[nobody].all()


def test_saturated_everywhere_is_flagged_with_lower_bound(scene, merged):
    sun = scene[..., 0] >= 1e8
    assert sun.sum() > 10 and merged.saturated[sun].all()
    core = binary_erosion(sun, iterations=2)  # pixels whose demosaic footprint is all sun
    assert core.any()
    np.testing.assert_allclose(merged.rgb[core], 1 / E_MIN, rtol=1e-6)  # the shortest frame's clip level
    assert merged.rgb[merged.saturated].max() <= 1 / E_MIN * (1 + 1e-6)  # never above the bound, never averaged
    assert merged.min_exposure_factor == pytest.approx(E_MIN)
    assert merged.saturated_fraction == pytest.approx(merged.saturated.mean())
    assert 0 < merged.saturated_fraction < 0.05
    assert any("saturated in every frame" in w for w in merged.warnings)


def test_exposure_factor_uses_time_iso_and_aperture(scene, tmp_path):
    # Same exposure factors reached through ISO and aperture; a different calibration constant.
    times = [1 / 4000, 1 / 4000, 1 / 1000, 1 / 250, 1 / 250]
    isos = [100, 400, 400, 400, 1600]
    stops = [8, 8, 8, 8, 8 / 2**0.5]
    paths = write_bracket(tmp_path, scene, times, iso=isos, f_number=stops, full_scale_radiance=10.0,
                          full_well_e=40000, seed=11)  # fmt: skip
    result = merge_bracket(paths)
    assert _median_rel_error(result, scene / 10.0) <= 0.02
    assert [f.iso for f in result.frames] == isos


def test_raw_frames_merge_like_files(bracket, merged):
    frames = []
    for path in bracket[::-1]:  # input order must not matter
        meta, mosaic = read_raw(path)
        frames.append(raw_frame(mosaic, exposure_s=meta.exposure_s, f_number=meta.f_number, iso=meta.iso,
                                black_level=meta.black_levels, white_level=meta.white_level, name=meta.path,
                                make=meta.make, model=meta.model))  # fmt: skip
    again = merge_bracket(frames, prefetch=False)
    np.testing.assert_array_equal(again.rgb, merged.rgb)
    np.testing.assert_array_equal(again.saturated, merged.saturated)


def test_to_rec709_uses_the_dng_colour_matrix(scene, tmp_path):
    xyz_to_camera = np.array([[0.9, 0.2, -0.1], [-0.3, 1.2, 0.1], [0.05, -0.1, 0.8]])
    paths = write_bracket(tmp_path, scene, EXPOSURES_S[1:5], camera_matrix=xyz_to_camera, seed=2)
    camera = merge_bracket(paths)
    rec709 = merge_bracket(paths, to_rec709=True)
    assert rec709.colour_space == "rec709"
    white = xyz_to_camera @ np.linalg.solve(XYZ_TO_REC709, np.ones(3))
    matrix = XYZ_TO_REC709 @ np.linalg.inv(np.round(xyz_to_camera, 4) / white.max())
    expected = np.maximum(camera.rgb @ matrix.T, 0)
    np.testing.assert_allclose(rec709.rgb, expected, rtol=1e-4, atol=1e-3)


def test_one_frame_and_mixed_brackets_are_rejected(scene, bracket, tmp_path):
    with pytest.raises(BracketError, match="at least 2 frames.*frame_00.dng"):
        merge_bracket(bracket[:1])
    other = write_bracket(tmp_path / "other", scene, [1 / 500], model="Other Body", prefix="b")
    with pytest.raises(BracketError, match="different cameras") as info:
        merge_bracket([bracket[0], other[0]])
    assert "frame_00.dng" in str(info.value) and "b_00.dng" in str(info.value)
    small = write_bracket(tmp_path / "small", scene[:64], [1 / 500], prefix="s")
    with pytest.raises(BracketError, match="size or CFA differ") as info:
        merge_bracket([bracket[3], small[0]])
    assert "frame_03.dng" in str(info.value) and "s_00.dng" in str(info.value)
    mosaic = np.zeros((8, 8), np.uint16)
    with pytest.raises(BracketError, match="no exposure_s"):
        merge_bracket([raw_frame(mosaic, exposure_s=0.01, f_number=8, iso=100, name="x"),
                       raw_frame(mosaic, exposure_s=None, f_number=8, iso=100, name="y")])  # fmt: skip


def test_corrupt_frame_in_bracket_names_the_file(bracket, tmp_path):
    bad = tmp_path / "cut.dng"
    bad.write_bytes(bracket[2].read_bytes()[:20000])
    with pytest.raises(RawError, match="cut.dng"):
        merge_bracket([bracket[0], bad, bracket[4]])


def test_shifted_frame_is_detected_and_aligned(scene, tmp_path):
    from scipy.ndimage import shift

    scenes = [scene] * 5
    scenes[1] = shift(scene, (3, -2, 0), order=1, mode="nearest")  # content moves down 3, left 2 pixels
    paths = write_bracket(tmp_path, scenes, EXPOSURES_S[1:6], seed=4)
    aligned = merge_bracket(paths)
    frame = aligned.frames[1]
    assert frame.aligned
    assert frame.shift_px == pytest.approx((3, -2), abs=0.3)
    assert aligned.status == "ok" and not any(f.moved for f in aligned.frames)
    assert all(not f.aligned for i, f in enumerate(aligned.frames) if i != 1)
    unaligned = merge_bracket(paths, align=False)
    assert unaligned.frames[1].moved and unaligned.status == "moved"
    err_aligned, err_unaligned = _median_rel_error(aligned, scene), _median_rel_error(unaligned, scene)
    assert err_aligned <= 0.02 and err_unaligned > 2 * err_aligned


def test_moving_object_marks_the_frame_moved(scene, tmp_path):
    scenes = [scene.copy() for _ in EXPOSURES_S]
    for i, frame in enumerate(scenes):
        x0 = 92 if i == 2 else 68
        frame[60:76, x0 : x0 + 18] = 150.0  # a grey object on the ground, elsewhere in frame 2
    paths = write_bracket(tmp_path, scenes, EXPOSURES_S, seed=7)
    result = merge_bracket(paths)
    assert result.status == "moved"
    assert result.frames[2].moved and result.frames[2].inconsistent_fraction > 0.02
    assert any("frame_02.dng" in w and "disagree" in w for w in result.warnings)
    assert all(f.shift_px is None or max(map(abs, f.shift_px)) < 0.5 for f in result.frames)  # no false global shift


def test_bench_merge_reports_both_timings(bracket):
    report = bench_merge(bracket[:3], repeat=1)
    assert report["frames"] == 3 and report["megapixels"] == pytest.approx(96 * 128 / 1e6)
    assert report["decode_s"] > 0 and report["merge_s"] > 0
    assert report["ratio"] == pytest.approx(report["merge_s"] / report["decode_s"])


def test_static_bracket_gets_no_shift_where_the_window_is_a_smooth_aureole(tmp_path):
    """Regression: with the alignment window (128 x 128 quads) smaller than the frame, the short
    frames' only well-exposed texture is the sun's smooth aureole, which agrees with itself within
    any loose tolerance at shifts of a few pixels; a static bracket must stay unshifted and keep
    its sun where the scene has it."""
    scene = synthetic_sky_scene(1224, 1632, seed=0)  # 2 MP, as `f2l bench-capture`; smaller aureoles are textured enough
    exposures = [2.0 ** (2 * k - 10) for k in range(5)]
    paths = write_bracket(tmp_path, scene, exposures, seed=0,
                          full_scale_radiance=float(np.percentile(scene, 50)) * 4.0 * max(exposures) / 64)
    result = merge_bracket(paths)
    assert not any(f.aligned for f in result.frames)
    assert all(f.shift_px is None or max(map(abs, f.shift_px)) < 0.25 for f in result.frames)
    lum = result.rgb.sum(axis=2)
    rows, cols = np.nonzero(lum >= 0.5 * lum.max())
    assert abs(rows.mean() - 0.25 * 1224) < 1.0 and abs(cols.mean() - 0.7 * 1632) < 1.0


def test_bracket_started_in_a_shared_pool_merges_like_paths_and_keeps_its_errors(bracket, merged, tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    from f2l.capture.merge import BracketStart

    fired = []
    with ThreadPoolExecutor(max_workers=2) as pool:
        started = BracketStart(bracket, pool, prefetch=2)
        assert started.submitted == 2  # decoding began before the merge
        started.when_all_submitted(lambda: fired.append("next"))
        assert not fired
        result = merge_bracket(started)
        assert fired == ["next"] and not started.pending
        np.testing.assert_array_equal(result.mosaic, merged.mosaic)
        np.testing.assert_array_equal(result.rgb, merged.rgb)
        lonely = BracketStart(bracket[:1], pool)
        lonely.when_all_submitted(lambda: fired.append("after error"))  # a failed bracket still hands on
        assert fired[-1] == "after error"
        with pytest.raises(BracketError, match="at least 2 frames"):
            merge_bracket(lonely)
