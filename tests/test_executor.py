"""One executor module for `f2l estimate` and `f2l build-dataset` (f2l.io.executor), and progress
as a callback (f2l.io.progress) that only the CLI draws (f2l.cli.progress)."""

from __future__ import annotations

import io

import pytest

from f2l.cli.progress import Bars
from f2l.io.executor import ExecutorUnavailable, check_executor, run_local
from f2l.io.progress import Progress, ProgressEvent
from f2l.io.shards import BadRecord


def test_one_executor_unavailable_for_both_runners():
    import f2l.estimate.ray_executor as est
    import f2l.pipeline.ray_build as build

    assert est.ExecutorUnavailable is ExecutorUnavailable is build.ExecutorUnavailable
    with pytest.raises(ValueError, match="'local' or 'ray'"):
        check_executor("dask")


def _stream(n, pulled):
    for i in range(n):
        pulled.append(i)
        yield (i, 2)


@pytest.mark.parametrize("workers", [1, 2])
def test_run_local_gives_every_result_with_bounded_tasks_in_flight(workers):
    pulled, results = [], []
    for r in run_local(pow, _stream(9, pulled), workers):
        results.append(r)
        assert len(pulled) - len(results) <= (0 if workers <= 1 else 2 * workers)
    assert sorted(results) == [i * i for i in range(9)]
    if workers == 1:
        assert results == [i * i for i in range(9)]  # serial: in order, here


def test_bad_record_rows_are_the_same_for_every_executor():
    from f2l.estimate.bad_rows import DUPLICATE_STATUS, bad_row
    from f2l.estimate.runner import _bad_row

    assert _bad_row is bad_row
    row = bad_row(BadRecord("s/part-0.parquet", "f1", "normals: not finite"), "sh9")
    assert (row["status"], row["message"], row["face_id"], row["source_path"]) == (
        "bad_record", "s/part-0.parquet (face 'f1'): normals: not finite", "f1", "s/part-0.parquet")
    assert bad_row(BadRecord("s", "f1", "duplicate face_id (first in t)"), "sh9")["status"] == DUPLICATE_STATUS


def test_progress_reports_to_a_callback_and_nothing_without_one():
    events: list[ProgressEvent] = []
    bar = Progress(events.append, "estimate", "estimate", 3)
    bar.advance(2)
    bar.note("[failed] f: no")
    bar.advance(1)
    assert [(e.done, e.advance, e.message) for e in events] == [(0, 0, None), (2, 2, None), (2, 0, "[failed] f: no"),
                                                              (3, 1, None)]
    assert {(e.stage, e.unit, e.total) for e in events} == {("estimate", "estimate", 3)}
    for off in (None, False):
        Progress(off, "x").advance()  # no callback: nothing, no error
    with pytest.raises(TypeError):
        Progress(True, "x")


def test_the_cli_draws_one_bar_per_task():
    out = io.StringIO()
    bars = Bars(file=out)
    for stage in ("fit faces", "estimate"):
        p = Progress(bars, stage, "photo", 2)
        p.note("error: bad.jpg: cannot read")
        p.advance(2)
    bars.close()
    text = out.getvalue()
    assert "fit faces" in text and "estimate" in text and text.count("error: bad.jpg") == 2 and "2/2" in text


def test_estimate_reports_progress_and_prints_nothing_itself(small_shards, tmp_path, capsys):
    from f2l.estimate.runner import run_estimates

    events: list[ProgressEvent] = []
    summary = run_estimates([small_shards], ["sh9"], tmp_path / "a", workers=1, threads=1, progress=events.append,
                            max_iter=2, joint="none")
    assert summary["ok"] == 4
    assert events[0].total == 4 and events[-1].done == 4 and sum(e.advance for e in events) == 4
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err == ""
