"""Seeded fuzzing of every reader of outside input (issue 40).

Each *target* starts from a valid file of its kind, made here, and feeds its reader mutated copies:
bytes flipped, cut, zeroed, repeated or inserted; and, for text formats, numbers swapped for NaN,
inf, 1e308 or a string, tables nested hundreds deep, strings of a megabyte, invalid UTF-8. The
reader must return a usable value or raise its documented error (``ExrError``, ``PhotoError``,
``RawError``, ``PipelineError``, ``InputError``, a ``ValueError`` naming the file); a shard reader
yields a ``BadRecord``. Anything else (``RecursionError``, ``MemoryError``, ``KeyError``, a crash
of the process, output on stdout, a value with NaN in it) is a failure, printed with its target,
case number and mutation so that it can be replayed.

Run under an address-space limit, so that a reader that allocates what a header claims fails::

    python tests/fuzzing.py --cases 40 --seed 0 --memory-gb 2      # the part in `make test`
    python tests/fuzzing.py --cases 2000 --seed 1 --memory-gb 2    # `make fuzz`
    python tests/fuzzing.py --target exr --cases 1 --seed 0 --first 17   # replay one case

The last line of stdout is a JSON summary; the exit code is 1 when any case failed.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import os
import re
import resource
import sys
import tempfile
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

# -- mutations -------------------------------------------------------------------------------------
NUMBER = re.compile(rb"(?<![\w.])-?\d+(\.\d+)?([eE][-+]?\d+)?(?![\w.])")
HOSTILE_NUMBERS = (b"nan", b"inf", b"-inf", b"1e308", b"-1e308", b"1e-308", b"0", b"-1", b"\"abc\"",
                   b"NaN", b"Infinity", b"[]", b"{}", b"99999999999999999999999")


def mutate_bytes(data: bytes, rng: np.random.Generator) -> tuple[str, bytes]:
    """One random byte-level mutation: (what was done, the new bytes)."""
    n = len(data)
    op = int(rng.integers(6))
    if n == 0:
        return "grow", bytes(rng.integers(0, 256, 64, dtype=np.uint8))
    at = int(rng.integers(n))
    if op == 0:
        k = int(rng.integers(1, 9))
        b = bytearray(data)
        for i in rng.integers(0, n, k):
            b[int(i)] ^= 1 << int(rng.integers(8))
        return f"flip {k} bits", bytes(b)
    if op == 1:
        return f"cut at {at}", data[:at]
    if op == 2:
        span = int(rng.integers(1, max(2, n // 8)))
        return f"zero {span} bytes at {at}", data[:at] + bytes(span) + data[at + span:]
    if op == 3:
        span = int(rng.integers(1, 64))
        return f"insert {span} random bytes at {at}", data[:at] + bytes(rng.integers(0, 256, span, dtype=np.uint8)) + data[at:]
    if op == 4:
        span = int(rng.integers(1, max(2, n // 4)))
        return f"repeat {span} bytes at {at}", data[:at + span] + data[at:at + span] + data[at + span:]
    span = int(rng.integers(1, 9))
    return f"0xff x{span} at {at}", data[:at] + b"\xff" * span + data[at + span:]


def mutate_text(data: bytes, rng: np.random.Generator, *, kind: str) -> tuple[str, bytes]:
    """One structure-aware mutation of a TOML or JSON text (``kind``), or a byte mutation."""
    op = int(rng.integers(6))
    numbers = list(NUMBER.finditer(data))
    if op == 0 and numbers:
        m = numbers[int(rng.integers(len(numbers)))]
        new = HOSTILE_NUMBERS[int(rng.integers(len(HOSTILE_NUMBERS)))]
        return f"number {m.group().decode()} -> {new.decode()}", data[:m.start()] + new + data[m.end():]
    if op == 1:
        depth = int(rng.choice([40, 1000, 100_000]))
        if kind == "json":
            deep = b"[" * depth + b"1" + b"]" * depth
            text = data.rstrip()
            return f"nested {depth} deep", (text[:-1] + b', "deep": ' + deep + b"}") if text.endswith(b"}") else deep
        deep = b"deep = " + b"{a = " * depth + b"1" + b"}" * depth + b"\n"
        return f"nested {depth} deep", deep + data
    if op == 2:
        size = int(rng.choice([70_000, 2_000_000]))
        s = b"x" * size
        if kind == "json":
            text = data.rstrip()
            return f"string of {size}", (text[:-1] + b', "long": "' + s + b'"}') if text.endswith(b"}") else s
        return f"string of {size}", b'long = "' + s + b'"\n' + data
    if op == 3:
        at = int(rng.integers(len(data) + 1))
        return f"invalid UTF-8 at {at}", data[:at] + b"\xff\xfe\xc3" + data[at:]
    if op == 4 and numbers:  # every number at once
        new = HOSTILE_NUMBERS[int(rng.integers(len(HOSTILE_NUMBERS)))]
        return f"every number -> {new.decode()}", NUMBER.sub(new, data)
    return mutate_bytes(data, rng)


# -- targets -----------------------------------------------------------------------------------------
@dataclass
class Target:
    """``make(folder)`` writes a valid seed file and returns its path; ``read(path)`` reads it and
    raises only ``allowed``; ``mutate`` is :func:`mutate_bytes` or a text mutation."""

    name: str
    make: Callable[[Path], Path]
    read: Callable[[Path], object]
    allowed: tuple[type[BaseException], ...]
    text: str | None = None  # "toml" / "json" for structure-aware mutation
    share: float = 1.0  # fraction of --cases run (commands cost more per case than readers)


class Unusable(AssertionError):
    """A reader returned a value it should have refused."""


def _finite(value, what: str) -> None:
    a = np.asarray(value)
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise Unusable(f"{what} has NaN or inf values")


def _sky(height: int = 16) -> np.ndarray:
    from f2l.lighting.grid import LatLongGrid
    from f2l.synth.skies import clear_sky

    return clear_sky(LatLongGrid(height, 2 * height), math.radians(40.0), 0.5, turbidity=3.0,
                     sun_kappa=64.0).astype(np.float32)


def _make_exr(folder: Path) -> Path:
    from f2l.io.exr import write_exr

    write_exr(folder / "seed.exr", _sky(), metadata={"f2l_note": "fuzz"})
    return folder / "seed.exr"


def _read_exr(path: Path):
    from f2l.io.exr import read_exr

    _finite(read_exr(path), "read_exr")


def _make_oiio(ext: str) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        import OpenImageIO as oiio

        path = folder / f"seed.{ext}"
        sky = _sky()
        out = oiio.ImageOutput.create(str(path))
        out.open(str(path), oiio.ImageSpec(sky.shape[1], sky.shape[0], 3, "float"))
        out.write_image(sky)
        out.close()
        return path
    return make


def _read_hdr(path: Path):
    from f2l.io.probe_io import read_hdr_image

    _finite(read_hdr_image(path), "read_hdr_image")


def _make_photo(ext: str) -> Callable[[Path], Path]:
    def make(folder: Path) -> Path:
        import skimage.data
        from PIL import Image

        path = folder / f"seed.{ext}"
        Image.fromarray(skimage.data.astronaut()[::4, ::4]).save(path)
        return path
    return make


def _read_photo(path: Path):
    from f2l.io.photo import load_photo

    photo = load_photo(path)
    _finite(photo.codes, "load_photo")


def _make_dng(folder: Path) -> Path:
    from f2l.capture.dng import write_bracket

    write_bracket(folder, np.full((32, 48, 3), 0.3, np.float32), [1 / 100], seed=1)
    return sorted(folder.glob("*.dng"))[0]


def _read_raw(path: Path):
    from f2l.io.raw_meta import read_raw_metadata

    meta = read_raw_metadata(path)
    for name in ("exposure_s", "f_number", "iso", "focal_length_mm", "white_level"):
        v = getattr(meta, name, None)
        if isinstance(v, float) and not math.isfinite(v):
            raise Unusable(f"read_raw_metadata: {name} = {v}")


SESSION_TOML = b"""probe_azimuth_deg = 12.5
timezone = "+02:00"
[lens]
projection = "equisolid"
focal_length_mm = 8.0
sensor_width_mm = 36.0
image_circle_radius_px = 482.7
principal_point_px = [768.0, 512.0]
falloff = {model = "polynomial", coefficients = [-0.2, -0.1], radius = "image_circle"}
[[shots]]
files = "sky/*"
pitch_deg = 90.0
yaw_deg = 0.0
roll_deg = 0.0
"""


def _make_session(folder: Path) -> Path:
    (folder / "session.toml").write_bytes(SESSION_TOML)
    return folder / "session.toml"


def _read_session(path: Path):
    from f2l.capture.session_toml import load_session_toml

    config, problem = load_session_toml(path.parent)
    if not isinstance(problem, str):
        raise Unusable(f"load_session_toml: problem is {type(problem).__name__}")
    json.dumps(config, allow_nan=False)  # no NaN or inf passed validation


def _make_pipeline(folder: Path) -> Path:
    from f2l.pipeline.spec import default_pipeline_path

    path = folder / "pipeline.toml"
    path.write_bytes(default_pipeline_path().read_bytes())
    return path


def _read_pipeline(path: Path):
    from f2l.pipeline.spec import load_pipeline

    load_pipeline(path)


SIDECAR = b'{"sun_direction": [0.3, 0.8, -0.52], "sun_elevation_deg": 53.1, "name": "probe", "tags": {"sky": "clear", "turbidity": 3.0}}'


def _make_json(folder: Path) -> Path:
    (folder / "seed.json").write_bytes(SIDECAR)
    return folder / "seed.json"


def _read_json(path: Path):
    from f2l.io.bounded import load_json

    load_json(path.read_bytes(), str(path))


def _make_shard(folder: Path) -> Path:
    from f2l.io.shards import FaceRecord, ShardWriter, pack_visibility

    rng = np.random.default_rng(0)
    n, gh, gw = 64, 8, 16
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    rec = FaceRecord(
        face_id="fuzz-0", source_path="photos/a.jpg", face_index=0, image_height=64, image_width=64,
        pixel_rc=np.stack([rng.integers(0, 64, n), rng.integers(0, 64, n)], 1).astype(np.int32),
        points=rng.normal(size=(n, 3)).astype(np.float32), normals=normals.astype(np.float32),
        observed_rgb=rng.random((n, 3)).astype(np.float32), mask=np.ones(n, bool), grid_height=gh,
        grid_width=gw, visibility_bits=pack_visibility(rng.random((n, gh * gw)) > 0.5),
        visibility_method="exact", gt_probe_path=None, photo_path=None, meta={"albedo": [0.5, 0.4, 0.3]})
    writer = ShardWriter(folder / "shards")
    writer.write(rec)
    return writer.close()[0]


def _read_shard(path: Path):
    from f2l.io.shards import BadRecord, FaceRecord, iter_records

    for rec in iter_records(path):
        if isinstance(rec, BadRecord):
            continue
        if not isinstance(rec, FaceRecord):
            raise Unusable(f"iter_records yielded {type(rec).__name__}")
        _finite(rec.observed_rgb, "record observed_rgb")
        _finite(rec.normals, "record normals")


# -- commands: the same mutations through the CLI, in this process ------------------------------------
COMMAND_EXIT_CODES = (0, 1, 4)
"""What a batch command may exit with on bad input (f2l.cli.common.exit_for): never 2 (usage)
for an input that is merely bad, never a traceback."""


def _invoke(args: list) -> dict:
    """Run ``f2l ARGS --json`` in this process; a traceback, another exit code or output that is
    not one JSON line is :class:`Unusable`. Returns the JSON summary."""
    from typer.testing import CliRunner

    from f2l.cli import app

    res = CliRunner().invoke(app, [str(a) for a in args] + ["--json"])
    if res.exception is not None and not isinstance(res.exception, SystemExit):
        tb = "".join(traceback.format_exception(res.exception)[-2:])
        raise Unusable(f"f2l {args[0]} raised {type(res.exception).__name__}: {tb[:400]}")
    if res.exit_code not in COMMAND_EXIT_CODES:
        raise Unusable(f"f2l {args[0]} exited {res.exit_code}: {res.output[-400:]}")
    try:
        return json.loads(res.stdout.strip().splitlines()[-1])
    except (ValueError, IndexError):
        raise Unusable(f"f2l {args[0]} --json printed no JSON summary: {res.stdout[-300:]!r}") from None


def _make_tree(folder: Path) -> Path:
    """A capture tree: a sky bracket (3 DNG frames) with the session.toml to be mutated, and a
    second, good session that must come through whatever the first holds."""
    from f2l.capture.dng import write_bracket

    for session in ("site", "good"):
        write_bracket(folder / "tree" / session / "sky", np.full((24, 32, 3), 0.3, np.float32),
                      [1 / 400, 1 / 100, 1 / 25], seed=2)
        (folder / "tree" / session / "session.toml").write_bytes(
            b'[lens]\nprojection = "equidistant"\nfov_deg = 180.0\n[[shots]]\nfiles = "sky/*"\npitch_deg = 90.0\n')
    return folder / "tree" / "site" / "session.toml"


def _ingest_and_make_probes(path: Path):
    import pyarrow.parquet as pq

    root, work = path.parents[1], path.parents[2] / "work"
    _invoke(["ingest", root, "--work", work, "--no-detect-roles"])
    _invoke(["make-probes", root, "--work", work, "--probe-height", "8"])
    rows = pq.read_table(work / "probes.parquet").to_pylist()
    good = [r for r in rows if r["session"] == "good"]
    if not good or any(r["status"] == "error" for r in good):
        raise Unusable(f"the good session was lost: {[(r['kind'], r['status'], r['message']) for r in good]}")


def _make_probe_folder(folder: Path) -> Path:
    from f2l.io.exr import write_exr

    probes = folder / "probes"
    probes.mkdir(exist_ok=True)
    write_exr(probes / "good.exr", _sky())
    write_exr(probes / "seed.exr", _sky())
    (probes / "seed.json").write_bytes(SIDECAR)
    return probes / "seed.exr"


def _fit_probe(path: Path):
    summary = _invoke(["eval", "fit-probe", path.parent, "-m", "sh9", "--grid", "16x32", "--out", path.parents[1] / "fitted"])
    if summary.get("ok", 0) < 1:
        raise Unusable(f"fit-probe lost the good probe: {str(summary)[:300]}")


def _make_sidecar_folder(folder: Path) -> Path:
    return _make_probe_folder(folder).with_suffix(".json")


def _make_photo_folder(folder: Path) -> Path:
    import skimage.data
    from PIL import Image

    photos = folder / "photos"
    photos.mkdir(exist_ok=True)
    face = Image.fromarray(skimage.data.astronaut()[:320, 64:384]).resize((200, 200))
    face.save(photos / "good.png")
    face.save(photos / "seed.jpg", quality=90)
    return photos / "seed.jpg"


def _fit_faces(path: Path):
    import pyarrow.parquet as pq

    out = path.parents[1] / "fitted"
    _invoke(["fit-faces", path.parent, "--out", out, "--grid", "8x16", "--resolution", "48", "--no-overlays"])
    rows = {r["source_path"].rsplit("/", 1)[-1]: r for r in pq.read_table(out / "status" / "fit_faces.parquet").to_pylist()}
    if rows.get("good.png", {}).get("status") != "ok":
        raise Unusable(f"fit-faces lost the good photo: {rows.get('good.png')}")


def _make_shard_pair(folder: Path) -> Path:
    good = _make_shard(folder / "a")
    bad = _make_shard(folder / "b")
    target = folder / "shards" / "seed.parquet"
    target.parent.mkdir(parents=True, exist_ok=True)
    good.replace(folder / "shards" / "good.parquet")
    bad.replace(target)
    import pyarrow.parquet as pq  # the second record gets its own face_id

    table = pq.read_table(target)
    pq.write_table(table.set_column(table.column_names.index("face_id"), "face_id",
                                    [["fuzz-1"] * table.num_rows]), target)
    return target


def _estimate(path: Path):
    summary = _invoke(["estimate", path.parent, "-m", "sh9", "--out", path.parents[1] / "est", "--workers", "1"])
    if summary.get("ok", 0) + summary.get("skipped_done", 0) < 1:
        raise Unusable(f"estimate lost the good record: {str(summary)[:300]}")


TARGET_NAMES = ("exr", "exr-any", "radiance", "pfm", "png", "jpeg", "dng", "session-toml", "pipeline-toml", "json",
                "shard", "cmd-ingest", "cmd-fit-probe", "cmd-fit-probe-side", "cmd-fit-faces", "cmd-estimate")
"""Every target, in the order a full run takes them (:func:`targets` builds them)."""


def targets() -> dict[str, Target]:
    from f2l.io.raw_meta import RawError
    from f2l.io.photo.core import PhotoError
    from f2l.io.bounded import InputError
    from f2l.io.exr import ExrError
    from f2l.pipeline.spec import PipelineError

    return {t.name: t for t in [
        Target("exr", _make_exr, _read_exr, (ExrError,)),
        Target("exr-any", _make_exr, _read_hdr, (ValueError, ExrError)),
        Target("radiance", _make_oiio("hdr"), _read_hdr, (ValueError,)),
        Target("pfm", _make_oiio("pfm"), _read_hdr, (ValueError,)),
        Target("png", _make_photo("png"), _read_photo, (PhotoError,)),
        Target("jpeg", _make_photo("jpg"), _read_photo, (PhotoError,)),
        Target("dng", _make_dng, _read_raw, (RawError,)),
        Target("session-toml", _make_session, _read_session, (), text="toml"),
        Target("pipeline-toml", _make_pipeline, _read_pipeline, (PipelineError,), text="toml"),
        Target("json", _make_json, _read_json, (InputError,), text="json"),
        Target("shard", _make_shard, _read_shard, ()),
        Target("cmd-ingest", _make_tree, _ingest_and_make_probes, (), text="toml", share=0.1),
        Target("cmd-fit-probe", _make_probe_folder, _fit_probe, (), share=0.1),
        Target("cmd-fit-probe-side", _make_sidecar_folder, _fit_probe, (), text="json", share=0.1),
        Target("cmd-fit-faces", _make_photo_folder, _fit_faces, (), share=0.05),
        Target("cmd-estimate", _make_shard_pair, _estimate, (), share=0.1),
    ]}


# -- the run -----------------------------------------------------------------------------------------
def _stdout_of(fn) -> tuple[str, BaseException | None]:
    """Run ``fn()`` with fd 1 captured (native libraries write there); (what it printed, error)."""
    sys.stdout.flush()
    saved = os.dup(1)
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 1)
        error = None
        try:
            fn()
        except BaseException as exc:  # noqa: BLE001 - judged by the caller
            error = exc
        finally:
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(saved)
        tmp.seek(0)
        return tmp.read().decode(errors="replace"), error


def run_target(target: Target, cases: int, seed: int, work: Path, first: int = 0) -> list[dict]:
    """Fuzz one target; the failures as dicts (target, case, mutation, error)."""
    folder = work / target.name
    folder.mkdir(parents=True, exist_ok=True)
    seed_path = target.make(folder)
    original = seed_path.read_bytes()
    failures = []
    printed, error = _stdout_of(lambda: target.read(seed_path))
    if error is not None or printed:
        return [{"target": target.name, "case": "seed", "mutation": "none",
                 "error": f"the valid seed file fails: {error!r} {printed[:200]!r}"}]
    progress = os.environ.get("F2L_FUZZ_PROGRESS")
    for case in range(first, first + max(1, round(cases * target.share))):
        if progress:  # the case in hand, for the parent to name if this process dies
            Path(progress).write_text(str(case))
        rng = np.random.default_rng([seed, case, sum(target.name.encode())])
        data, what = original, []
        for _ in range(int(rng.integers(1, 3))):
            op, data = (mutate_text(data, rng, kind=target.text) if target.text
                        else mutate_bytes(data, rng))
            what.append(op)
        seed_path.write_bytes(data)
        printed, error = _stdout_of(lambda: target.read(seed_path))
        problem = None
        if printed.strip():
            problem = f"wrote to stdout: {printed.strip()[:200]!r}"
        elif isinstance(error, Unusable):
            problem = str(error)
        elif error is not None and not isinstance(error, target.allowed):
            tb = traceback.format_exception(error)
            problem = f"{type(error).__name__}: {str(error)[:200]} | {''.join(tb[-2:])[:300]}"
        elif error is not None and str(seed_path) not in str(error) and target.allowed:
            problem = f"the error does not name the file: {str(error)[:300]}"
        if problem:
            failures.append({"target": target.name, "case": case, "mutation": "; ".join(what),
                             "error": problem})
    seed_path.write_bytes(original)
    return failures


def _run_isolated(name: str, args) -> tuple[dict, list[dict]]:
    """One target in a child process (its own address-space limit and crashes): (its entry in the
    summary, its failures). A child that dies is a failure naming the case it was on."""
    import subprocess

    with tempfile.NamedTemporaryFile(prefix="f2l-fuzz-case-") as progress:
        cmd = [sys.executable, str(Path(__file__).resolve()), "--target", name, "--cases", str(args.cases),
               "--seed", str(args.seed), "--first", str(args.first), "--memory-gb", str(args.memory_gb)]
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, text=True, env=dict(os.environ, F2L_FUZZ_PROGRESS=progress.name))
        try:
            child = json.loads(proc.stdout.strip().splitlines()[-1])
            return child["targets"][name], child["failures"]
        except (ValueError, IndexError, KeyError):
            case = Path(progress.name).read_text().strip() or "?"
            how = f"signal {-proc.returncode}" if proc.returncode < 0 else f"exit {proc.returncode}"
            return ({"cases": 0, "failures": 1, "seconds": None},
                    [{"target": name, "case": case, "mutation": "(see the replay)",
                      "error": f"the process died ({how}) on this case; replay: python tests/fuzzing.py --target "
                               f"{name} --first {case} --cases 1 --seed {args.seed}"}])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=40, help="mutated inputs per target")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--first", type=int, default=0, help="first case number (to replay one case)")
    ap.add_argument("--target", action="append", help="only these targets (repeatable)")
    ap.add_argument("--memory-gb", type=float, default=2.0, help="address-space limit (0: none)")
    args = ap.parse_args(argv)
    names = args.target or list(TARGET_NAMES)
    summary = {"seed": args.seed, "cases_per_target": args.cases, "memory_gb": args.memory_gb,
               "targets": {}, "failures": []}
    if len(names) > 1:  # each target in its own process: its own limit, and a crash is one target's failure
        for name in names:
            entry, failures = _run_isolated(name, args)
            summary["targets"][name] = entry
            summary["failures"].extend(failures)
    else:
        if args.memory_gb > 0:
            limit = int(args.memory_gb * 2**30)
            resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
        target = targets()[names[0]]
        with tempfile.TemporaryDirectory(prefix="f2l-fuzz-") as tmp:
            t0 = time.perf_counter()
            failures = run_target(target, args.cases, args.seed, Path(tmp), args.first)
            n = max(1, round(args.cases * target.share))
            summary["targets"][target.name] = {"cases": n, "failures": len(failures),
                                               "seconds": round(time.perf_counter() - t0, 2)}
            summary["failures"].extend(failures)
            print(f"{target.name:18s} {n:5d} cases  {len(failures):3d} failures  "
                  f"{time.perf_counter() - t0:6.1f} s", file=sys.stderr, flush=True)
    for f in summary["failures"][:50]:
        print(f"FAIL {f['target']} case {f['case']} ({f['mutation']}): {f['error']}", file=sys.stderr)
    shown = dict(summary, failures=summary["failures"][:20])  # the first few; stderr lists 50
    print(json.dumps(shown))
    return 1 if summary["failures"] else 0


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    sys.exit(main())
