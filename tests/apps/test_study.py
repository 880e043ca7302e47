"""Studies: shake and calibration sweeps, resumable CSVs, identical results on a process pool and on Dask."""

import csv

import cv2
import pytest

from lfgraph.cli import main

pytestmark = pytest.mark.slow  # end-to-end runs (`make test-fast` leaves them out)

SHAKE = ["study", "shake", "--scene", "small-2x2", "--rot-deg", "0,0.5", "--trans-mm", "0,1", "--trials", "1",
         "--stages", "paper,default", "--quiet"]


def rows(path):
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_shake_study_pool_and_dask_give_identical_csvs(tmp_path):
    local, dask = tmp_path / "local.csv", tmp_path / "dask.csv"
    assert main([*SHAKE, "--jobs", "2", "-o", str(local)]) == 0
    assert main([*SHAKE, "--jobs", "2", "--executor", "dask-local", "-o", str(dask)]) == 0
    assert local.read_bytes() == dask.read_bytes()
    data = rows(local)
    assert len(data) == 2 * 2  # two levels x two schedules
    by = {(r["stages"], r["level"]): r for r in data}
    # the shake is real and the default schedule removes it; the paper's schedule leaves more behind
    assert float(by[("default", "1")]["transfer_before_px"]) > 0.2
    assert float(by[("default", "1")]["transfer_px"]) < float(by[("paper", "1")]["transfer_px"])
    assert cv2.imread(str(tmp_path / "local.png")) is not None  # the figure beside the CSV, PNG and PDF
    assert (tmp_path / "local.pdf").read_bytes().startswith(b"%PDF")


def test_shake_study_resumes(tmp_path):
    out = tmp_path / "s.csv"
    args = [*SHAKE, "--stages", "default", "--jobs", "1", "-o", str(out)]
    assert main(args) == 0
    full = out.read_text()
    # an interrupted run: only the first trial's row made it to disk
    lines = full.splitlines(keepends=True)
    out.write_text("".join(lines[:2]))
    assert main(args) == 0
    assert out.read_text() == full
    # nothing left to do: the CSV is not rewritten
    mtime = out.stat().st_mtime_ns
    assert main(args) == 0
    assert out.stat().st_mtime_ns == mtime


def test_shake_study_save_rrd(tmp_path):
    import rerun as rr

    rrd = tmp_path / "study.rrd"
    assert main([*SHAKE, "--stages", "default", "--jobs", "1", "-o", str(tmp_path / "s.csv"),
                 "--save", str(rrd)]) == 0
    with rr.server.Server(datasets={"s": [str(rrd)]}) as server:
        names = [c.name for c in server.client().get_dataset("s").schema()]
    assert any(n.startswith("/study/default_none/transfer_px") for n in names)


def test_calibration_study(tmp_path, capsys):
    out = tmp_path / "c.csv"
    assert main(["study", "calibration", "--scene", "small-2x2", "--frames", "4,8", "--sigma-px", "0.1",
                 "--trials", "2", "--jobs", "2", "-o", str(out)]) == 0
    data = rows(out)
    assert {r["method"] for r in data} == {"paper", "joint", "cramer-rao", "calibrateMultiview"}
    assert len(data) == 4 * 2 * 2
    text = capsys.readouterr().out
    assert "RMS over seeds" in text

    def rms(method, key, frames):
        vals = [float(r[key]) ** 2 for r in data if r["method"] == method and r["frames"] == str(frames)]
        return (sum(vals) / len(vals)) ** 0.5

    assert rms("joint", "pos_err_mm", 8) < rms("paper", "pos_err_mm", 8)
    assert rms("joint", "pos_err_mm", 8) < rms("joint", "pos_err_mm", 4) * 1.5  # more frames do not hurt
    assert cv2.imread(str(tmp_path / "c.png")) is not None
    assert (tmp_path / "c.pdf").read_bytes().startswith(b"%PDF")


@pytest.mark.parametrize("bad", [["--executor", "spark"], ["--executor", "dask://nohost"], ["--stages", "bundle"],
                                 ["--robust", "hubber"], ["--rot-deg", "0,1,2", "--trans-mm", "0,1"]])
def test_bad_study_options(tmp_path, bad):
    with pytest.raises(SystemExit) as exc:
        main([*SHAKE, "-o", str(tmp_path / "x.csv"), *bad])
    assert exc.value.code == 2
    assert not (tmp_path / "x.csv").exists()
