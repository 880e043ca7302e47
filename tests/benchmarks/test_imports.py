"""Every benchmark script imports cleanly (`make bench` is not part of `make test`, so a renamed constant would
otherwise break it unnoticed)."""

import subprocess
import sys
from pathlib import Path

BENCH_DIR = Path(__file__).resolve().parents[2] / "benchmarks"


def test_every_benchmark_imports():
    names = sorted(p.stem for p in BENCH_DIR.glob("*.py"))
    assert "run_all" in names and "render" in names
    code = "import importlib, sys\n" + "".join(f"importlib.import_module({n!r})\n" for n in names)
    result = subprocess.run([sys.executable, "-c", code], cwd=BENCH_DIR, capture_output=True, text=True, check=False)
    assert result.returncode == 0, result.stderr[-2000:]
