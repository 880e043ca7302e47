"""Fleet scale: check and refine many recordings (one per camera array) on a process pool or a Dask cluster.

A manifest CSV names each recording (columns ``camera``, ``calibration``, ``capture``; paths relative to the
manifest; optional ``layout``, ``max_frames``, ``max_px``, ``tolerance_px``). For each camera the drift check
runs first; when it finds drift, the refinement runs and, when that improves the calibration, the refined
calibration is written next to the input as a new version (``NAME.v2.json``, ``NAME.v3.json``, ...; never over
the input, atomically, through a hidden temporary removed at once). One row per camera goes into the results CSV
(sorted, rewritten atomically after every camera; a re-run skips cameras already in it), with a verdict:

- ``OK``: the drift check confirms every view within ``tolerance_px`` (its verdict OK), or finds no view DRIFTED (a
  change both significant and above ``tolerance_px`` at infinity, default 0.1 px: the rule of `lfgraph refine` and
  `lfgraph check`) and the reprojection RMS is <= ``max_px``;
- ``DRIFTED``: a view drifted (or the RMS is above ``max_px``) and the refinement changed the calibration (views
  confirmed by held-out tracks; the new version's path is in the row);
- ``UNCERTAIN``: it did not fit, but the refinement could not improve it (too little texture, too few frames):
  inspect the recording;
- ``ERROR``: the recording or calibration could not be used (the message is in the row); other cameras go on.

A refined version stores what it was made from (``metrics["fleet_source"]``: the input calibration's SHA-256, the
capture, the options): a run killed between writing a version and writing its row is resumed by reusing that
version, never by writing another. A run that fails (a full disk, Ctrl-C) leaves nothing new: a results file it
created is removed, and so is every version it wrote that no row of the remaining results names. One run at a time
writes a results file (an exclusive lock beside it, ``.NAME.lock``, removed when the run ends); a second is refused
with a message.

Results do not depend on the executor or on the order in which cameras finish (every step is deterministic), except
the ``seconds`` column. Paths in the results are relative to the manifest's folder.
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import json
import os
import tempfile
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lfgraph.core.files import default_mode, deferred_interrupt, input_problem, process_alive
from lfgraph.core.verdict import Verdict

MANIFEST_COLUMNS = ("camera", "calibration", "capture")
RESULT_COLUMNS = ("camera", "verdict", "rms_before_px", "rms_after_px", "max_rotation_change_deg",
                  "max_position_change_mm", "view_changes", "refined_calibration", "frames", "seconds", "error")
VERDICTS = (Verdict.OK, Verdict.DRIFTED, Verdict.UNCERTAIN, Verdict.ERROR)  # a camera's (`Verdict`)
DEFAULT_MAX_PX = 0.5  # the drift check's threshold, as `lfgraph check --max-px`
DEFAULT_MAX_FRAMES = 3
DEFAULT_TOLERANCE_PX = 0.1  # as RefineConfig.tolerance_px: a drift must move the transfer at infinity by more
MAX_VERSIONS = 10_000  # calibration versions tried before giving up (a folder that is filling up with them)


class ManifestError(ValueError):
    """A manifest that cannot be used; the message names the file, line and column."""


@dataclass(frozen=True)
class FleetItem:
    """One manifest row, paths resolved against the manifest's folder."""

    camera: str
    calibration: Path
    capture: Path
    layout: str = "auto"
    max_frames: int = DEFAULT_MAX_FRAMES
    max_px: float = DEFAULT_MAX_PX
    root: Path = Path(".")  # the manifest's folder: result paths are written relative to it
    tolerance_px: float = DEFAULT_TOLERANCE_PX


def read_manifest(path: str | os.PathLike) -> list[FleetItem]:
    """Parse a manifest CSV.

    Raises:
        ManifestError: unreadable file, missing columns, an empty or repeated camera, a bad number (named by line).
    """
    path = Path(path)
    problem = input_problem(path)
    if problem is not None:  # a FIFO would block the read forever
        raise ManifestError(f"{path}: {problem}")
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ManifestError(f"{path}: cannot read the manifest ({exc})") from None
    reader = csv.DictReader(text.splitlines())
    names = [str(n).strip() for n in (reader.fieldnames or [])]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ManifestError(f"{path}: the manifest names the column(s) {', '.join(twice)} more than once; which one "
                            f"holds the value is not clear")
    missing = [c for c in MANIFEST_COLUMNS if c not in (reader.fieldnames or [])]
    if missing:
        raise ManifestError(f"{path}: the manifest needs the columns {', '.join(MANIFEST_COLUMNS)}; missing "
                            f"{', '.join(missing)} (found {', '.join(reader.fieldnames or []) or 'none'})")
    items, seen = [], {}
    for row in reader:
        line = reader.line_num
        camera = (row.get("camera") or "").strip()
        if not camera:
            raise ManifestError(f"{path}, line {line}: empty camera name")
        if camera in seen:
            raise ManifestError(f"{path}, line {line}: camera {camera!r} is listed twice (also line {seen[camera]})")
        seen[camera] = line
        for col in ("calibration", "capture"):
            if not (row.get(col) or "").strip():
                raise ManifestError(f"{path}, line {line}: empty {col} for camera {camera!r}")
        try:
            max_frames = int(row.get("max_frames") or DEFAULT_MAX_FRAMES)
            max_px = float(row.get("max_px") or DEFAULT_MAX_PX)
            tolerance_px = float(row.get("tolerance_px") or DEFAULT_TOLERANCE_PX)
        except ValueError as exc:
            raise ManifestError(f"{path}, line {line}: {exc}") from None
        if max_frames < 1 or not (np.isfinite(max_px) and max_px > 0):
            raise ManifestError(f"{path}, line {line}: max_frames must be >= 1 and max_px > 0")
        if not (np.isfinite(tolerance_px) and tolerance_px >= 0):
            raise ManifestError(f"{path}, line {line}: tolerance_px must be >= 0, got {tolerance_px:g}")
        base = path.parent
        given = row["calibration"].strip()
        target = (base / given).resolve()
        if not Path(given).is_absolute() and base.resolve() not in target.parents:
            raise ManifestError(f"{path}, line {line}: calibration {given!r} climbs out of the manifest's folder "
                                f"{base}; the fleet writes new versions beside the calibrations, so a relative path "
                                f"must stay inside it (an absolute path says where on purpose)")
        items.append(FleetItem(camera, base / row["calibration"].strip(), base / row["capture"].strip(),
                               (row.get("layout") or "auto").strip(), max_frames, max_px, base, tolerance_px))
    if not items:
        raise ManifestError(f"{path}: the manifest lists no camera")
    return items


def _version_base(calibration: Path) -> str:
    """``NAME`` of ``NAME.json`` or ``NAME.vN.json``."""
    stem = calibration.stem
    return stem.rsplit(".v", 1)[0] if ".v" in stem and stem.rsplit(".v", 1)[1].isdigit() else stem


def _versions(calibration: Path) -> Iterator[Path]:
    """``NAME.v2.json``, ``NAME.v3.json``, ... beside ``calibration`` (whose own version suffix is dropped)."""
    base = _version_base(calibration)
    for n in range(2, MAX_VERSIONS):
        yield calibration.with_name(f"{base}.v{n}{calibration.suffix}")


def next_version(calibration: Path) -> Path:
    """``NAME.vN.json`` beside ``calibration`` for the first N >= 2 that is free (the input is version 1)."""
    for candidate in _versions(calibration):
        if not candidate.exists():
            return candidate
    raise OSError(f"{calibration.parent}: {MAX_VERSIONS} versions of {calibration.stem} already; clean the folder")


def source_key(item: FleetItem) -> dict[str, Any]:
    """What a refined version was made from: the input calibration's bytes (SHA-256), the capture and the options
    that decide the result. A re-run that finds a version with the same key reuses it instead of writing another."""
    digest = hashlib.sha256(Path(item.calibration).read_bytes()).hexdigest()
    return {"calibration_sha256": digest, "capture": os.path.relpath(item.capture, item.root),
            "max_frames": item.max_frames, "tolerance_px": item.tolerance_px}


def existing_version(input_path: Path, key: dict[str, Any]) -> Path | None:
    """A version beside ``input_path`` that a run interrupted before its results row was written made from the same
    source (``metrics["fleet_source"]`` equal to ``key``), or None."""
    for candidate in _versions(input_path):
        if not candidate.exists():
            return None
        try:
            stored = json.loads(candidate.read_text(encoding="utf-8")).get("metrics", {}).get("fleet_source")
        except (OSError, ValueError, AttributeError):
            continue
        if stored == key:
            return candidate
    return None


def _save_new_version(calib: Any, input_path: Path, key: dict[str, Any] | None = None) -> Path:
    """Write ``calib`` as the next free version, atomically and without ever replacing an existing file; with
    ``key`` (`source_key`) stored in its metrics, and an earlier version of the same source reused.

    The text goes to a hidden temporary beside it (``.NAME.vN.json.PID.XXXX.tmp``), hard-linked to the version's
    name (which fails when another worker took it meanwhile) and then removed: on success only the version is left.
    """
    if key is not None:
        found = existing_version(input_path, key)
        if found is not None:
            return found
        calib = calib.replace(metrics={**dict(calib.metrics or {}), "fleet_source": key})
    text = calib.to_json()
    for _ in range(MAX_VERSIONS):
        target = next_version(input_path)
        with deferred_interrupt():  # created and in the charge of the ``try`` below, or not created
            fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.{os.getpid()}.", suffix=".tmp", dir=target.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as fh:
                fh.write(text)
            os.chmod(tmp, default_mode(0o666))  # mkstemp makes it 0600
            try:
                os.link(tmp, target)
            except FileExistsError:
                continue
            return target
        finally:
            with deferred_interrupt():
                os.unlink(tmp)
    raise OSError(f"could not write a new version of {input_path}")


def process_camera(item: FleetItem) -> list[dict[str, Any]]:
    """Check one camera's recording, refine on drift, write the new version; one result row (never raises)."""
    from lfgraph.core.calibration import Calibration
    from lfgraph.core.grid_design import free_when_not_parallel
    from lfgraph.io.capture import open_capture
    from lfgraph.judge.check import check
    from lfgraph.rectification.checks import check_compatible
    from lfgraph.refinement import RefineConfig, refine

    start = time.perf_counter()
    row: dict[str, Any] = {"camera": item.camera, "verdict": Verdict.ERROR, "rms_before_px": float("nan"),
                           "rms_after_px": float("nan"), "max_rotation_change_deg": 0.0,
                           "max_position_change_mm": 0.0, "view_changes": "{}", "refined_calibration": "",
                           "frames": 0, "error": ""}
    try:
        calib, _ = free_when_not_parallel(Calibration.load(item.calibration))  # a ring stored as a row: its poses'
        capture = open_capture(item.capture, calib.grid, item.layout)
        check_compatible(calib, capture.grid, capture.image_sizes, str(item.capture))
        config = RefineConfig(max_frames=item.max_frames, tolerance_px=item.tolerance_px)
        report = check(calib, capture.frames(item.max_frames), config=config)
        row.update(rms_before_px=report.rms_px, frames=report.frames)
        # OK: every view confirmed within the tolerance, or none drifted and the residuals within max_px
        if report.verdict == Verdict.OK or (not report.drifted() and report.rms_px <= item.max_px):
            row.update(verdict=Verdict.OK, rms_after_px=report.rms_px, view_changes=_verdicts_json(report.verdicts))
        else:
            refined, ref_report = refine(calib, capture.frames(item.max_frames), config)
            rot, pos = _changes(calib, refined)
            row.update(rms_after_px=ref_report.rms_after_px if ref_report.accepted else report.rms_px,
                       max_rotation_change_deg=float(rot.max()), max_position_change_mm=float(pos.max()),
                       view_changes=_verdicts_json(ref_report.verdicts))
            if ref_report.accepted and (rot.max() > 0 or pos.max() > 0):  # some view really changed
                written = _save_new_version(refined, item.calibration, source_key(item))
                row.update(verdict=Verdict.DRIFTED, refined_calibration=os.path.relpath(written, item.root))
            else:
                row.update(verdict=Verdict.UNCERTAIN, error="; ".join(ref_report.warnings))
    except Exception as exc:  # one bad recording must never stop the fleet: it becomes an ERROR row
        row.update(verdict=Verdict.ERROR, error=f"{type(exc).__name__}: {exc}")
    row["seconds"] = time.perf_counter() - start
    return [row]


def _verdicts_json(verdicts: Sequence[Any]) -> str:
    """Per view: verdict, significance and posterior sigmas (JSON, sorted keys: identical across executors)."""
    out = {}
    for v in verdicts:
        d = v.as_dict()
        out[v.name] = {k: d[k] for k in ("verdict", "change_sigma", "rotation_change_deg", "position_change_mm",
                                         "sigma_rotation_deg", "sigma_position_mm") if k in d}
    return json.dumps(out, sort_keys=True)


def _changes(before: Any, after: Any) -> tuple[np.ndarray, np.ndarray]:
    from lfgraph.core.geometry import rotation_angle_deg

    rot = np.asarray(rotation_angle_deg(np.swapaxes(before.ref_T_view[:, :3, :3], 1, 2)
                                        @ after.ref_T_view[:, :3, :3]))
    pos = 1e3 * np.linalg.norm(after.ref_T_view[:, :3, 3] - before.ref_T_view[:, :3, 3], axis=1)
    return rot, pos


def run_fleet(manifest: str | os.PathLike, results_csv: str | os.PathLike, executor: str = "local",
              jobs: int | None = None, progress: bool = True) -> list[dict[str, Any]]:
    """Process every camera of ``manifest`` not yet in ``results_csv``; returns all result rows.

    A run that fails (any exception, Ctrl-C) leaves nothing new (`_undo`): the results file if it created it, the
    versions it wrote that no remaining row names, its temporaries; the lock is removed in any case.

    Args:
        manifest: the manifest CSV (see the module docstring).
        results_csv: the results CSV, created or resumed.
        executor: ``local`` (a process pool), ``dask-local`` or ``dask://HOST:PORT``.
        jobs: processes / Dask workers (default: all cores).

    Raises:
        ManifestError: a bad manifest; ValueError: a results CSV of another kind, or another run holding it.
    """
    from lfgraph.apps.study import run_study

    items = read_manifest(manifest)
    results_csv = Path(results_csv)
    with _exclusive(results_csv):
        existed = results_csv.exists()
        before = {v for item in items for v in _existing_versions(item.calibration)}
        try:
            return run_study(items, process_camera, results_csv, RESULT_COLUMNS, _item_rows, _row_key, executor,
                             jobs, progress)
        except BaseException:
            with deferred_interrupt():
                _undo(items, results_csv, existed, before)
            raise


@contextlib.contextmanager
def _exclusive(results_csv: Path) -> Iterator[None]:
    """Hold the results file's lock (``.NAME.lock`` beside it) for the block; refuse when another run holds it. The
    lock file is removed at the end, before it is unlocked: a run that opened it meanwhile and then gets the lock
    sees that the name is gone (or is another file) and locks the current one instead, so two runs never both hold
    "the" lock."""
    import fcntl

    lock_path = results_csv.with_name(f".{results_csv.name}.lock")
    while True:
        with deferred_interrupt():
            lock = open(lock_path, "a+")  # noqa: SIM115  (closed below, after the block)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.close()
            raise ValueError(f"{results_csv}: another fleet run is writing these results (lock {lock_path}); wait "
                             f"for it to finish, or give this run its own results file") from None
        held = os.fstat(lock.fileno())
        with contextlib.suppress(FileNotFoundError):
            named = os.stat(lock_path)
            if (named.st_ino, named.st_dev) == (held.st_ino, held.st_dev):
                break
        lock.close()
    try:
        yield
    finally:
        with deferred_interrupt():
            with contextlib.suppress(OSError):
                lock_path.unlink()
            lock.close()


def _existing_versions(calibration: Path) -> list[Path]:
    """The versions beside ``calibration`` (``NAME.v2.json`` ... up to the first missing one)."""
    out = []
    for candidate in _versions(Path(calibration)):
        if not candidate.exists():
            return out
        out.append(candidate)
    return out


def _undo(items: Sequence[FleetItem], results_csv: Path, existed: bool, before: set[Path]) -> None:
    """After a failed run: remove the results file if this run created it, every version this run wrote (new since
    the run began, made from this camera's source) that no row of the remaining results names, and the temporaries
    of its workers (they are stopped by now: their process is gone)."""
    from lfgraph.apps.study import read_rows

    if not existed:
        results_csv.unlink(missing_ok=True)
    try:
        rows = read_rows(results_csv, RESULT_COLUMNS) if results_csv.exists() else []
    except (OSError, ValueError):
        return  # results that cannot be read: keep every version rather than guess
    root = items[0].root  # result paths are relative to the manifest's folder
    named = {(root / r["refined_calibration"]).resolve() for r in rows if r.get("refined_calibration")}
    for item in items:
        with contextlib.suppress(OSError):
            key = source_key(item)
            for version in _existing_versions(item.calibration):
                if version in before or version.resolve() in named:
                    continue
                stored = json.loads(version.read_text(encoding="utf-8")).get("metrics", {}).get("fleet_source")
                if stored == key:
                    version.unlink()
        for tmp in Path(item.calibration).parent.glob(f".{_version_base(item.calibration)}.v*.tmp"):
            pid = tmp.name[1:-len(".tmp")].rsplit(".", 2)[-2]  # .NAME.vN.json.PID.XXXX.tmp
            if pid.isdigit() and tmp.is_file() and not process_alive(int(pid)):
                with contextlib.suppress(OSError):
                    tmp.unlink()


def _item_rows(item: FleetItem) -> set[tuple]:
    return {(item.camera,)}


def _row_key(row: dict) -> tuple:
    return (str(row["camera"]),)


def summarise(rows: Sequence[dict[str, Any]]) -> dict[str, int]:
    """Cameras per verdict."""
    counts = {v: 0 for v in VERDICTS}
    for r in rows:
        counts[str(r["verdict"])] = counts.get(str(r["verdict"]), 0) + 1
    return counts
