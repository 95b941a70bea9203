import os
import tempfile

import numpy as np
import pytest

from f2l.lighting.grid import LatLongGrid

SMALL_GRID = LatLongGrid(32, 64)

# f2l's per-user cache (the registry's capability-check stamps) in a folder of this run's own, so
# the suite neither reads nor writes ~/.cache/f2l (subprocesses inherit it)
os.environ.setdefault("F2L_CACHE_DIR", tempfile.mkdtemp(prefix="f2l-test-cache-"))


@pytest.fixture(scope="session")
def small_grid():
    return SMALL_GRID


@pytest.fixture(scope="session")
def small_shards(tmp_path_factory):
    """Four synthetic faces (64 px photos, 32x64 grid) written as shards, seed 7."""
    from f2l.synth.dataset import write_synthetic_shards

    out = tmp_path_factory.mktemp("shards")
    summary = write_synthetic_shards(out, n=4, seed=7, grid=SMALL_GRID, image_size=64, overcast_fraction=0.25,
                                     progress=False)
    assert summary["faces"] == 4
    return out


@pytest.fixture(scope="session")
def face_geometry():
    """A rendered synthetic face (geometry + transport) under a clear sky, 32x64 grid."""
    from f2l.synth.render import render_face
    from f2l.synth.skies import clear_sky

    from f2l.lighting.grid import direction_from_angles

    probe = clear_sky(SMALL_GRID, np.radians(40.0), np.radians(60.0))
    sun = direction_from_angles(np.radians(40.0), np.radians(60.0))
    rng = np.random.default_rng(3)
    info = {"kind": "clear", "sun_direction": [float(v) for v in sun]}
    return render_face(SMALL_GRID, probe, rng, image_size=80, head_pose_deg=(10.0, -5.0, 3.0), sun_direction=sun,
                       sky_info=info)
