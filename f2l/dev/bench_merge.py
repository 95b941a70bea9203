"""Bracket merge run time against a bare LibRaw decode of the same files (the merge's own floor).

:func:`bench_merge` times, best of ``repeat``, ``rawpy.imread(p).raw_image_visible`` for every frame
of a bracket against :func:`f2l.capture.merge.merge_bracket` of it; ``f2l dev bench-capture``
(:mod:`f2l.dev.bench_capture`) times whole captures the same way in child processes.
"""

from __future__ import annotations

import math
import os
import timeit
from collections.abc import Sequence

from f2l.capture.merge import merge_bracket
from f2l.io.raw_meta import read_raw_metadata

__all__ = ["bench_merge"]


def bench_merge(paths: Sequence[str | os.PathLike], *, repeat: int = 3, **merge_kwargs) -> dict:
    """Time bare ``rawpy.imread(p).raw_image_visible`` over ``paths`` against :func:`merge_bracket`.

    Returns best-of-``repeat`` seconds ``decode_s`` and ``merge_s`` (metadata + decode + merge +
    demosaic + motion check), their ``ratio``, the bracket's ``frames`` and ``megapixels`` per frame.
    """
    import rawpy

    def decode_all() -> None:
        for p in paths:
            with rawpy.imread(os.fspath(p)) as raw:
                raw.raw_image_visible  # noqa: B018 (the decode being timed)

    decode_all()  # warm the file cache
    decode_s = min(timeit.repeat(decode_all, number=1, repeat=max(1, repeat)))
    merge_s = min(timeit.repeat(lambda: merge_bracket(paths, **merge_kwargs), number=1, repeat=max(1, repeat)))
    meta = read_raw_metadata(paths[0], levels=False)
    return {"frames": len(paths), "megapixels": meta.width * meta.height / 1e6, "decode_s": decode_s,
            "merge_s": merge_s, "ratio": merge_s / decode_s if decode_s > 0 else math.inf}  # fmt: skip
