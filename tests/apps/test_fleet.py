"""Fleet: a manifest of recordings checked and refined on a process pool or Dask, verdicts against the truth,
identical results across executors, resume, an error row for a bad recording, versions never over the input."""

import csv
import shutil

import pytest

from lfgraph.apps.fleet import ManifestError, next_version, read_manifest, run_fleet
from lfgraph.cli import EXIT_OK, main

pytestmark = pytest.mark.slow  # end-to-end runs (`make test-fast` leaves them out)

SHAKE_DEG = "1.0"  # well above what the 0.5 px check threshold lets through on the small rig


@pytest.fixture(scope="module")
def fleet_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("fleet")
    for name, shake, seed in (("still", "0", "1"), ("knocked", SHAKE_DEG, "2")):
        assert main(["synth", "scene", str(root / name), "--scene", "small-2x2", "--frames", "2", "--seed", seed,
                     "--shake-rot-deg", shake, "--shake-trans-mm", "1" if shake != "0" else "0", "--jobs", "2",
                     "--quiet"]) == 0
    (root / "broken.json").write_text("{ not json")
    rows = [("cam-still", "still/truth.json", "still"), ("cam-knocked", "knocked/original.json", "knocked"),
            ("cam-broken", "broken.json", "still")]
    with (root / "manifest.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["camera", "calibration", "capture", "max_frames"])
        writer.writerows([(*r, 2) for r in rows])
    return root


def rows_without_time(path):
    with open(path, newline="") as fh:
        return [{k: v for k, v in r.items() if k != "seconds"} for r in csv.DictReader(fh)]


def test_fleet_verdicts_versions_resume_and_executors(fleet_dir, tmp_path):
    work = tmp_path / "pool"
    shutil.copytree(fleet_dir, work)
    original = (work / "knocked" / "original.json").read_bytes()
    assert main(["fleet", str(work / "manifest.csv"), "-o", str(work / "results.csv"), "--jobs", "2",
                 "--quiet"]) == EXIT_OK
    rows = {r["camera"]: r for r in rows_without_time(work / "results.csv")}
    assert rows["cam-still"]["verdict"] == "OK"
    assert rows["cam-knocked"]["verdict"] == "DRIFTED"
    assert rows["cam-broken"]["verdict"] == "ERROR" and "broken.json" in rows["cam-broken"]["error"]
    version = work / "knocked" / "original.v2.json"
    assert rows["cam-knocked"]["refined_calibration"] == "knocked/original.v2.json" and version.exists()
    assert (work / "knocked" / "original.json").read_bytes() == original  # never over the input
    assert float(rows["cam-knocked"]["rms_after_px"]) < float(rows["cam-knocked"]["rms_before_px"])
    # a re-run skips every camera already in the results: nothing changes, no new version
    before = (work / "results.csv").read_text()
    run_fleet(work / "manifest.csv", work / "results.csv", "local", 1, progress=False)
    assert (work / "results.csv").read_text() == before and not (work / "knocked" / "original.v3.json").exists()
    # a local Dask cluster gives the same results (all but the timing column)
    dask_work = tmp_path / "dask"
    shutil.copytree(fleet_dir, dask_work)
    run_fleet(dask_work / "manifest.csv", dask_work / "results.csv", "dask-local", 2, progress=False)
    expected = [{k: v.replace(str(work), str(dask_work)) for k, v in r.items()}  # error texts name the folder
                for r in rows_without_time(work / "results.csv")]
    assert rows_without_time(dask_work / "results.csv") == expected


def test_bad_manifests_are_named(tmp_path):
    bad = tmp_path / "m.csv"
    bad.write_text("camera,calibration\nA,a.json\n")
    with pytest.raises(ManifestError, match=r"m.csv: the manifest needs the columns .* missing capture"):
        read_manifest(bad)
    bad.write_text("camera,calibration,capture\nA,a.json,x\nA,b.json,y\n")
    with pytest.raises(ManifestError, match=r"line 3: camera 'A' is listed twice"):
        read_manifest(bad)
    bad.write_text("camera,calibration,capture,max_px\nA,a.json,x,zero\n")
    with pytest.raises(ManifestError, match="line 2"):
        read_manifest(bad)
    # issue 42: a column named twice (which value counts?) was accepted
    bad.write_text("camera,calibration,capture,max_px,max_px\nA,a.json,x,1,2\n")
    with pytest.raises(ManifestError, match=r"names the column\(s\) max_px more than once"):
        read_manifest(bad)
    # issue 27: `../../` paths wrote versions outside the manifest's tree
    bad.write_text("camera,calibration,capture\nA,../../a.json,x\n")
    with pytest.raises(ManifestError, match=r"line 2: calibration '../../a.json' climbs out of the manifest's folder"):
        read_manifest(bad)


def test_versions_count_up_and_never_reuse_a_name(tmp_path):
    calib = tmp_path / "cam.json"
    calib.write_text("{}")
    assert next_version(calib).name == "cam.v2.json"
    (tmp_path / "cam.v2.json").write_text("{}")
    assert next_version(calib).name == "cam.v3.json"
    assert next_version(tmp_path / "cam.v2.json").name == "cam.v3.json"


def test_an_interrupted_run_is_resumed_without_orphans_and_runs_do_not_collide(fleet_dir, tmp_path):
    """Issue 27: Ctrl-C after a version was written but before its results row left an orphaned v2 and the re-run
    wrote v3 for the same drift; two runs on one results file both exited 0 and the first run's rows were lost."""
    import fcntl

    work = tmp_path / "w"
    shutil.copytree(fleet_dir, work)
    manifest, results = work / "manifest.csv", work / "results.csv"
    run_fleet(manifest, results, "local", 1, progress=False)
    assert (work / "knocked" / "original.v2.json").exists()
    results.unlink()  # as if the run had been stopped between writing v2 and writing its row
    run_fleet(manifest, results, "local", 1, progress=False)
    rows = {r["camera"]: r for r in rows_without_time(results)}
    assert rows["cam-knocked"]["refined_calibration"] == "knocked/original.v2.json"
    assert not (work / "knocked" / "original.v3.json").exists()  # the same source: v2 reused, nothing orphaned
    # another run holding the results file: this one is refused, nothing of the first is lost
    before = results.read_text()
    with open(work / ".results.csv.lock", "a+") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        with pytest.raises(ValueError, match="another fleet run"):
            run_fleet(manifest, results, "local", 1, progress=False)
        assert main(["fleet", str(manifest), "-o", str(results), "--quiet"]) != EXIT_OK
    assert results.read_text() == before


def test_a_knock_within_the_tolerance_is_ok(fleet_dir, tmp_path):
    """Issue 42: with ``tolerance_px`` 100 a knocked camera's changes are within the tolerance: OK (it said UNCERTAIN:
    the residuals above ``max_px`` sent it to a refinement that, rightly, changed nothing)."""
    work = tmp_path / "tol"
    shutil.copytree(fleet_dir, work)
    with (work / "manifest.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(["camera", "calibration", "capture", "max_frames", "tolerance_px"])
        writer.writerow(["cam-knocked", "knocked/original.json", "knocked", 2, 100])
    run_fleet(work / "manifest.csv", work / "results.csv", "local", 1, progress=False)
    (row,) = rows_without_time(work / "results.csv")
    assert row["verdict"] == "OK" and not row["refined_calibration"]
    assert not (work / "knocked" / "original.v2.json").exists()
