"""The command-line demo `python -m lievi demo`."""

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

import lievi
from lievi._cli import build_parser, demo, problems
from lievi._cli import main as cli_main


@pytest.mark.extended  # 33 s
def test_demo_in_process_json_and_plot(tmp_path, capsys):
    pytest.importorskip("matplotlib")
    plot, table = tmp_path / "demo.png", tmp_path / "demo.json"
    args = build_parser().parse_args(
        ["demo", "--steps", "50", "--plot", str(plot), "--json", str(table)]
    )
    assert demo.main(args) == 0

    out = capsys.readouterr().out
    assert "Hairer–Lubich–Wanner" in out
    assert "device:" in out

    document = json.loads(table.read_text(encoding="utf-8"))
    assert document["problem"]["n_steps"] == 50
    assert math.isclose(document["problem"]["T"], 5.0)
    rows = document["rows"]
    assert [row["integrator"] for row in rows] == [name for name, _ in problems.INTEGRATORS]
    for row in rows:
        assert row["integrator"] in out
        assert row["result"] == 0
        assert row["failed_step"] == -1
        for key in (
            "error_m",
            "error_g",
            "energy_drift",
            "casimir_drift",
            "spatial_momentum_drift",
            "orthogonality_end",
            "newton_per_step",
            "time_first_s",
            "time_second_s",
        ):
            assert isinstance(row[key], float) and math.isfinite(row[key]), (row["integrator"], key)
        # h = 0.1 to T = 5 with second-order methods: small but nonzero errors.
        assert 0 < row["error_m"] < 0.1
        assert 0 < row["error_g"] < 0.1
        if row["integrator"] == "RK4 (non-geometric)":
            assert row["casimir_drift"] > 1e-9  # the baseline drifts, visibly even at T = 5
        else:
            assert row["casimir_drift"] < 1e-12
        if row["del_residual_max"] is not None:
            assert row["del_residual_max"] < 1e-12

    assert plot.exists() and plot.stat().st_size > 0
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow  # ~50 s: the demo's full run (CI runs the demo itself)
def test_demo_reports_failure(tmp_path, capsys):
    # h = 2.5: the first step turns the body by h·|ω₀| = 3.39 rad, inside the largest step
    # bound of the methods (the order-6 composition's 3.93, so the command line takes it)
    # but past π: the exponential chart reports `step_too_large` at step 0, as data.
    table = tmp_path / "demo.json"
    assert cli_main(["demo", "--steps", "3", "--h", "2.5", "--json", str(table)]) == 1
    out = capsys.readouterr().out
    assert "failed at step 0" in out
    rows = {row["integrator"]: row for row in json.loads(table.read_text())["rows"]}
    assert rows["DEP exp chart"]["result"] == lievi.RESULTS.step_too_large
    assert rows["DEP exp chart"]["error_m"] is None  # NaN is written as null


@pytest.mark.slow  # CI runs the demo command itself; this adds the stdout checks
def test_demo_subprocess():
    env = dict(os.environ, PYTHONIOENCODING="utf-8")
    proc = subprocess.run(
        [sys.executable, "-m", "lievi", "demo", "--steps", "20"],
        capture_output=True,
        text=True,
        encoding="utf-8",
        env=env,
        timeout=600,  # a hang guard; the run compiles every integrator (slow on a loaded machine)
    )
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert any(line.startswith("integrator") for line in lines)
    for name, _ in problems.INTEGRATORS:
        row = [line for line in lines if line.startswith(name)]
        assert len(row) == 1, proc.stdout
        assert row[0].split()[-3] == "0"  # result code column


BAD_ARGUMENTS = [
    (["demo", "--steps", "0"], "--steps"),
    (["demo", "--steps", "1.5"], "--steps"),
    (["demo", "--steps", "100000000000000000000000"], "--steps"),
    (["demo", "--h", "-1"], "--h"),
    (["demo", "--h", "0"], "--h"),
    (["demo", "--h", "nan"], "--h"),
    (["demo", "--h", "inf"], "--h"),
    (["demo", "--h", "1e-320"], "smallest normal"),  # subnormal
    (["demo", "--h", "1e9", "--steps", "1"], "step bound"),
    (["demo", "--h", "3000"], "step bound"),
    (["demo", "--problem", "heavy-top", "--h", "3"], "step bound"),
    (["demo", "--h", "2", "--steps", "1000"], "T = h·N"),
    (["demo", "--problem", "control", "--h", "0.1"], "--steps"),
    (["demo", "--problem", "control", "--steps", "100000"], "--steps"),
    (["demo", "--problem", "nope"], "--problem"),
    ([], "COMMAND"),
]


@pytest.mark.parametrize("argv, names", BAD_ARGUMENTS)
def test_cli_rejects_bad_arguments(argv, names, capsys, monkeypatch):
    """Every bad option ends in one error line (exit status 2) before any computation."""
    ran = []
    monkeypatch.setattr(lievi, "reference_solution", lambda *a, **k: ran.append(a))
    monkeypatch.setattr(demo, "main", lambda args: ran.append(args))
    with pytest.raises(SystemExit) as exit_:
        cli_main(argv)
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    (line,) = [line for line in err.splitlines() if "error:" in line]
    assert line.startswith("python -m lievi") and names in line, err
    assert "Traceback" not in err and not ran


def test_cli_step_bound_names_the_largest_step(capsys):
    with pytest.raises(SystemExit):
        cli_main(["demo", "--h", "3000"])
    line = capsys.readouterr().err.splitlines()[-1]
    largest = float(line.rsplit("--h ≤ ", 1)[1])
    body, _, m0 = problems.hlw_problem()
    rate = float(np.linalg.norm(body.velocity(m0)))
    bound = max(i.step_bound() for _, i in problems.INTEGRATORS)
    assert largest == pytest.approx(bound / rate, rel=1e-2)


@pytest.mark.slow  # ~50 s: the demo's full run (CI runs the demo itself)
def test_demo_heavy_top(tmp_path, capsys):
    """`--problem heavy-top`: every integrator that takes a potential, the heavy top's
    Casimirs |Γ|² and Π·Γ kept to round-off by the Lie–Poisson integrators, the energy
    (with V) bounded, the DEL residual (with V) at round-off."""
    table = tmp_path / "top.json"
    args = build_parser().parse_args(
        ["demo", "--problem", "heavy-top", "--steps", "40", "--json", str(table)]
    )
    assert demo.main(args) == 0
    out = capsys.readouterr().out
    assert "heavy top" in out and "Π·Γ" in out
    document = json.loads(table.read_text(encoding="utf-8"))
    assert document["problem"]["name"] == "asymmetric heavy top"
    assert document["problem"]["center_of_mass"] == list(problems.CENTER_OF_MASS)
    rows = {row["integrator"]: row for row in document["rows"]}
    expected = [
        name
        for name, i in problems.INTEGRATORS
        if not isinstance(i, lievi.PreprocessedMoserVeselov)
    ]
    assert list(rows) == expected
    for name, row in rows.items():
        assert row["result"] == 0 and 0 < row["error_m"] < 0.1, name
        assert 0 < row["energy_drift"] < 1e-2, name  # bounded O(h²) energy error, V included
        if name == "RK4 (non-geometric)":
            assert row["gamma_norm_defect"] > 1e-12  # RK4 leaves the group
        else:
            assert row["gamma_norm_defect"] <= 1e-12
            assert row["vertical_momentum_drift"] <= 1e-12, name
        if row["del_residual_max"] is not None:
            assert row["del_residual_max"] <= 1e-12, name


def test_demo_checks_output_paths_before_the_run(tmp_path, capsys, monkeypatch):
    """A bad --json/--plot path is reported before any computation (exit status 2)."""
    ran = []
    monkeypatch.setattr(demo, "run_integrator", lambda *a, **k: ran.append(a))
    missing = tmp_path / "no" / "such" / "dir" / "out.json"
    with pytest.raises(SystemExit) as exit_:
        cli_main(["demo", "--steps", "3", "--json", str(missing), "--plot", str(tmp_path)])
    assert exit_.value.code == 2
    err = capsys.readouterr().err
    assert "--json" in err and "does not exist" in err
    assert "--plot" in err and "is a directory" in err
    assert not ran


@pytest.mark.slow  # ~50 s: the demo's full run (CI runs the demo itself)
def test_demo_bad_json_keeps_the_plot(tmp_path, capsys, monkeypatch):
    """A --json that fails while writing (after the checks) does not lose the --plot."""
    pytest.importorskip("matplotlib")

    def fail(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(demo, "write_json", fail)
    plot = tmp_path / "demo.png"
    args = build_parser().parse_args(
        ["demo", "--steps", "3", "--json", str(tmp_path / "t.json"), "--plot", str(plot)]
    )
    assert demo.main(args) == 1
    captured = capsys.readouterr()
    assert "disk full" in captured.err and "--json" in captured.err
    assert plot.exists() and plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
def test_demo_binary(tmp_path, capsys):
    """`--problem binary`: two bodies in mutual gravity on SE(3)²; the geometric methods
    keep the total angular and linear momentum to round-off, RK4 does not; the DEL
    residual of the product's discrete Lagrangian at round-off."""
    table = tmp_path / "binary.json"
    args = build_parser().parse_args(
        ["demo", "--problem", "binary", "--steps", "40", "--json", str(table)]
    )
    assert demo.main(args) == 0
    assert "binary asteroid" in capsys.readouterr().out
    document = json.loads(table.read_text(encoding="utf-8"))
    assert document["problem"]["name"] == "binary asteroid"
    rows = {row["integrator"]: row for row in document["rows"]}
    assert list(rows) == [name for name, _ in problems.PROBLEMS["binary"].integrators]
    for name, row in rows.items():
        assert row["result"] == 0 and 0 < row["error_m"] < 1e-2, name
        if name == "RK4 (non-geometric)":
            assert row["angular_momentum_drift"] > 1e-12
        else:
            assert row["angular_momentum_drift"] <= 1e-12, name
            assert row["linear_momentum_change"] <= 1e-12, name
        if row["del_residual_max"] is not None:
            assert row["del_residual_max"] <= 1e-12, name
