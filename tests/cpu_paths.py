"""Run the test suite under other CPUs' floating-point code paths, one machine (`make test-cpu-paths`).

A result must not depend on which kernels the CPU selects: OpenBLAS (numpy, scipy) picks its
kernels by CPU model, torch's ATen picks a vectorisation level, and MKL (torch's BLAS) its own
instruction set. Each profile below forces one such choice through the libraries' documented
environment variables and runs the default suite in a fresh process, so the rounding of the
machines the project meets can be checked here. Not part of `make test` (CI runs only that).

    OPENBLAS_CORETYPE      OpenBLAS DYNAMIC_ARCH kernel (Zen maps to the Haswell kernel,
                           Prescott to the generic SSE3 "Katmai" one)
    ATEN_CPU_CAPABILITY    default (no SIMD dispatch), avx2, avx512
    MKL_ENABLE_INSTRUCTIONS  SSE4_2, AVX2, AVX512 (an upper bound on what MKL may use)

``native`` leaves the environment as it is; ``auto`` removes OPENBLAS_CORETYPE/OPENBLAS_L2_SIZE,
which some machines here set, so OpenBLAS detects the CPU itself (SkylakeX on an AVX-512 EPYC).

Usage: python tests/cpu_paths.py [--profile NAME ...] [--report FILE] [-- PYTEST ARGS]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import time
from pathlib import Path

UNSET = None
PROFILES: dict[str, dict[str, str | None]] = {
    "native": {},
    "auto": {"OPENBLAS_CORETYPE": UNSET, "OPENBLAS_L2_SIZE": UNSET},
    "haswell-avx2": {"OPENBLAS_CORETYPE": "Haswell", "ATEN_CPU_CAPABILITY": "avx2",
                     "MKL_ENABLE_INSTRUCTIONS": "AVX2"},
    "skylakex-avx512": {"OPENBLAS_CORETYPE": "SkylakeX", "ATEN_CPU_CAPABILITY": "avx512",
                        "MKL_ENABLE_INSTRUCTIONS": "AVX512"},
    "skylakex-avx2": {"OPENBLAS_CORETYPE": "SkylakeX", "ATEN_CPU_CAPABILITY": "avx2"},
    "zen-default": {"OPENBLAS_CORETYPE": "Zen", "ATEN_CPU_CAPABILITY": "default"},
    "prescott-sse": {"OPENBLAS_CORETYPE": "Prescott", "ATEN_CPU_CAPABILITY": "default",
                     "MKL_ENABLE_INSTRUCTIONS": "SSE4_2"},
}
SUMMARY = re.compile(r"^=*\s*(\d+ (passed|failed).*?)\s*=*$")


def profile_env(name: str) -> dict[str, str]:
    env = dict(os.environ)
    for key, value in PROFILES[name].items():
        if value is None:
            env.pop(key, None)
        else:
            env[key] = value
    return env


def kernels(env: dict[str, str]) -> str:
    """What the libraries report they run under ``env`` (OpenBLAS kernel, ATen capability)."""
    probe = ("import numpy, torch; from threadpoolctl import threadpool_info; "
             "b = [i.get('architecture') for i in threadpool_info() if i['internal_api'] == 'openblas']; "
             "print(f\"openblas={','.join(map(str, b))} aten={torch.backends.cpu.get_cpu_capability()}\")")
    out = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True)
    return out.stdout.strip() or f"(probe failed: {out.stderr.strip()[-200:]})"


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra: list[str] = []
    if "--" in argv:
        cut = argv.index("--")
        argv, extra = argv[:cut], argv[cut + 1:]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--profile", action="append", choices=sorted(PROFILES), help="default: all")
    parser.add_argument("--report", type=Path, default=Path("build/cpu_paths.md"))
    args = parser.parse_args(argv)
    names = args.profile or list(PROFILES)
    rows, failed = [], 0
    for name in names:
        env = profile_env(name)
        seen = kernels(env)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *extra],
                              env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t0
        lines = [ln for ln in proc.stdout.splitlines() if SUMMARY.match(ln.strip())]
        summary = SUMMARY.match(lines[-1].strip()).group(1) if lines else f"exit {proc.returncode}"
        fails = [ln for ln in proc.stdout.splitlines() if ln.startswith("FAILED") or ln.startswith("ERROR")]
        failed += proc.returncode != 0
        rows.append((name, seen, summary, wall, fails))
        print(f"{name:16s} {seen:32s} {summary}  ({wall:.0f} s)", flush=True)
        for ln in fails:
            print(f"    {ln}", flush=True)
    args.report.parent.mkdir(parents=True, exist_ok=True)
    with open(args.report, "w") as fh:
        fh.write("| profile | environment | kernels seen | result | wall |\n|---|---|---|---|---|\n")
        for name, seen, summary, wall, _ in rows:
            setting = ", ".join(f"{k}={'(unset)' if v is None else v}" for k, v in PROFILES[name].items()) or "as is"
            fh.write(f"| {name} | {setting} | {seen} | {summary} | {wall:.0f} s |\n")
    print(f"report: {args.report}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
