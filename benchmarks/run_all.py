"""`make bench`: run every benchmark script in this folder and report which failed its targets."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

BENCHMARKS = ["cli_speed.py", "render.py", "detection.py", "calibration.py", "calibrate_speed.py", "rectify.py",
              "refine.py", "sweep.py", "middlebury_pairs.py", "ring.py", "real.py", "opencv_multiview.py", "fleet.py",
              "targetless.py"]


def main() -> int:
    here = Path(__file__).parent
    failed = []
    for name in BENCHMARKS:
        path = here / name
        if not path.exists():
            continue
        print(f"=== {name}", flush=True)
        if subprocess.run([sys.executable, str(path)], check=False).returncode != 0:
            failed.append(name)
    print("benchmarks missing their targets: " + (", ".join(failed) if failed else "none"))
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
