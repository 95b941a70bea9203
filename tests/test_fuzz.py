"""The seeded fuzzing of every reader of outside input (tests/fuzzing.py), fast part; `make fuzz`
runs a longer one."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path


def test_fuzzed_readers_fail_only_with_their_documented_errors():
    """Every reader (60 mutated inputs each) and batch command (3-6 each: ingest + make-probes,
    fit-probe with bad probes and side files, fit-faces, estimate) under a 2 GB address-space limit,
    ~30 s. A failure prints its target, case and mutation; replay it with ``python tests/fuzzing.py
    --target T --first C --cases 1``."""
    script = Path(__file__).with_name("fuzzing.py")
    proc = subprocess.run([sys.executable, str(script), "--cases", "60", "--seed", "0", "--memory-gb", "2"],
                          capture_output=True, text=True, timeout=600)
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert len(summary["targets"]) >= 16 and {"cmd-ingest", "cmd-estimate"} <= set(summary["targets"])
    assert all(t["cases"] >= 3 for t in summary["targets"].values())
    failed = [f"{f['target']} case {f['case']} ({f['mutation']}): {f['error']}" for f in summary["failures"]]
    assert proc.returncode == 0 and not failed, "\n".join(failed[:10]) + "\n" + proc.stderr[-3000:]
