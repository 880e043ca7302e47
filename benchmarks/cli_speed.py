"""Start-up and demo time against their targets (issue 16): `lfgraph --help` <= 0.3 s (it imports neither GTSAM,
OpenCV nor rerun), and the whole `lfgraph demo` <= 45 s on an idle 2-core machine (rendering included).

Run: ``python benchmarks/cli_speed.py [--no-demo]``. Prints a table with the machine's load average beside the
times (a loaded machine misses wall-time targets it meets idle); exit 1 when a target is missed.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

from lfgraph.cli.tables import format_table

HELP_TARGET_S = 0.3
DEMO_TARGET_S = 45.0
HELP_RUNS = 5


def timed(cmd: list[str]) -> float:
    start = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - start


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--no-demo", action="store_true", help="skip the demo (it takes a minute)")
    args = parser.parse_args()
    rows, failures = [], []
    help_s = min(timed([sys.executable, "-m", "lfgraph", "--help"]) for _ in range(HELP_RUNS))
    peer_s = min(timed([sys.executable, "-c", "import cv2, gtsam"]) for _ in range(HELP_RUNS))
    rows.append(["lfgraph --help (best of 5)", f"{help_s:.2f}", f"{HELP_TARGET_S:g}",
                 f"import cv2, gtsam alone: {peer_s:.2f} s ({peer_s / help_s:.1f}x)"])
    if help_s > HELP_TARGET_S:
        failures.append(f"--help {help_s:.2f} s")
    if not args.no_demo:
        with tempfile.TemporaryDirectory() as tmp:
            demo_s = timed([sys.executable, "-m", "lfgraph", "demo", "--out", tmp, "--quiet"])
        rows.append(["lfgraph demo (render, calibrate, rectify, refine)", f"{demo_s:.1f}", f"{DEMO_TARGET_S:g}", ""])
        if demo_s > DEMO_TARGET_S:
            failures.append(f"demo {demo_s:.0f} s")
    load = os.getloadavg()[0]
    print(format_table(["what", "seconds", "target_s", "peer"], rows))
    print(f"load average {load:.1f} on {os.cpu_count()} cores (wall times are for an idle machine)")
    print("targets missed: " + (", ".join(failures) if failures else "none"))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
