"""Issue 40: ``lfgraph -q COMMAND`` prints nothing on standard output when it succeeds — every command, not just
calibrate, whose tables and "wrote" lines were the first fixed — with errors still on standard error and the same exit
codes; ``--json`` keeps the document it was asked for."""

import json

import pytest

from lfgraph.cli import EXIT_BAD_INPUT, EXIT_OK, build_parser, main


def _commands() -> set[str]:
    """Every command of the parser, with its subcommand where it has them (``synth scene``, ``study shake``)."""
    parser = build_parser()
    (sub,) = [a for a in parser._actions if a.dest == "command"]  # argparse keeps subparsers here
    names = set()
    for name, p in sub.choices.items():
        inner = [a for a in p._actions if getattr(a, "choices", None) and isinstance(a.choices, dict)]
        names |= {f"{name} {s}" for s in inner[0].choices} if inner else {name}
    return names


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """The smallest inputs every command accepts: boards and a scene of small-2x2 (six frames: calibrate-scene's
    least), with their truth."""
    root = tmp_path_factory.mktemp("quiet")
    assert main(["-q", "synth", "checkerboard", str(root / "boards"), "--scene", "small-2x2", "--frames", "10",
                 "--seed", "3", "--jobs", "1"]) == EXIT_OK
    assert main(["-q", "synth", "scene", str(root / "scene"), "--scene", "small-2x2", "--frames", "6", "--jobs",
                 "1"]) == EXIT_OK
    (root / "manifest.csv").write_text("camera,calibration,capture,max_frames\ncam,scene/truth.json,scene,2\n")
    return root


def _runs(r) -> list[tuple[str, list, int]]:
    """(command, arguments, exit code) in an order where each run's outputs are the next ones' inputs."""
    board = ["--grid", "2x2", "--board", "7x5", "--square-mm", "15", "--jobs", "1"]
    scene, truth = r / "scene", r / "scene" / "truth.json"
    return [
        ("synth checkerboard", ["synth", "checkerboard", r / "b2", "--scene", "small-2x2", "--frames", "2"], EXIT_OK),
        ("synth scene", ["synth", "scene", r / "s2", "--scene", "small-2x2", "--frames", "1"], EXIT_OK),
        ("info", ["info", r / "boards" / "truth.json"], EXIT_OK),
        ("calibrate", ["calibrate", r / "boards", *board, "-o", r / "c.json"], EXIT_OK),
        ("evaluate", ["evaluate", r / "c.json", "--truth", r / "boards" / "truth.json"], EXIT_OK),
        ("calibrate-scene", ["calibrate-scene", scene, "--grid", "2x2", "--pitch-mm", "10", "--focal-px", "300",
                             "-o", r / "cs.json"], EXIT_OK),
        ("rectify", ["rectify", truth, scene, "-o", r / "rect", "--jobs", "1"], EXIT_OK),
        ("check", ["check", truth, scene, "--max-frames", "2"], EXIT_OK),
        ("refine", ["refine", truth, scene, "-o", r / "refined.json", "--max-frames", "2"], EXIT_OK),
        ("fleet", ["fleet", r / "manifest.csv", "-o", r / "fleet.csv", "--jobs", "1"], EXIT_OK),
        ("depth-error", ["depth-error", "--focal-px", "800", "--baseline-m", "0.1", "--error-px", "0.5"], EXIT_OK),
        ("study shake", ["study", "shake", "--scene", "small-2x2", "--trials", "1", "--rot-deg", "0.5", "--trans-mm",
                         "0", "--stages", "default", "--jobs", "1", "-o", r / "shake.csv"], EXIT_OK),
        ("study calibration", ["study", "calibration", "--scene", "small-2x2", "--frames", "5", "--sigma-px", "0.1",
                               "--trials", "1", "--jobs", "1", "-o", r / "cal.csv"], EXIT_OK),
        ("export", ["export", r / "c.json", "--to", "opencv-yaml", "-o", r / "c.yml"], EXIT_OK),
        ("import", ["import", r / "c.yml", "--from", "opencv-yaml", "-o", r / "back.json"], EXIT_OK),
        ("demo", ["demo", "--scene", "small-2x2", "--out", r / "demo", "--jobs", "1", "--no-refine"], EXIT_OK),
    ]


@pytest.mark.slow
def test_every_command_is_silent_on_stdout_under_q(inputs, capsys):
    runs = _runs(inputs)
    assert {name for name, _, _ in runs} == _commands(), "a command without a quiet run here"
    for name, args, code in runs:
        assert main(["-q", *map(str, args)]) == code, (name, capsys.readouterr().err)
        out = capsys.readouterr()
        assert out.out == "", f"lfgraph -q {name} printed: {out.out[:300]!r}"
        assert "%|" not in out.err, f"lfgraph -q {name} showed a progress bar"


def test_q_keeps_errors_on_stderr_and_the_exit_code(tmp_path, capsys):
    code = main(["-q", "info", str(tmp_path / "missing.json")])
    out = capsys.readouterr()
    assert code == EXIT_BAD_INPUT and out.out == "" and "missing.json" in out.err


def test_q_keeps_what_json_asked_for(tmp_path, capsys):
    code = main(["-q", "depth-error", "--focal-px", "800", "--baseline-m", "0.1", "--error-px", "0.5", "--json"])
    assert code == EXIT_OK and json.loads(capsys.readouterr().out)["focal_px"] == 800
    assert main(["-q", "depth-error", "--focal-px", "800", "--baseline-m", "0.1", "--error-px", "0.5"]) == EXIT_OK
    assert capsys.readouterr().out == ""
