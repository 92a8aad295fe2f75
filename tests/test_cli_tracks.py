"""`cfrace tracks list|show`: the real CLI (in-process with typer's CliRunner, and the installed
entry point in a subprocess for exit codes and error lines)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from cfrace.cli.main import app
from cfrace.paths import TRACKS_DIR

CFRACE = Path(sys.executable).with_name("cfrace")
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
runner = CliRunner()


def run_cli(*args, home: Path | None = None):
    env = dict(os.environ, COLUMNS="200")
    if home is not None:
        env["CFRACE_HOME"] = str(home)
    return subprocess.run([str(CFRACE), *args], capture_output=True, text=True, env=env, timeout=120)


def test_list_shows_both_tracks_with_counts():
    result = runner.invoke(app, ["tracks", "list"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    lines = {line.split("│")[1].strip(): line for line in result.output.splitlines() if line.count("│") >= 5}
    assert "complex" in lines and "lemniscate" in lines
    assert [c.strip() for c in lines["complex"].split("│")[2:5]] == ["6", "4", "11 x 18 x 3"]
    assert [c.strip() for c in lines["lemniscate"].split("│")[2:5]] == ["6", "2", "5 x 7 x 3"]


def test_show_prints_gates_in_race_order_with_notes():
    result = runner.invoke(app, ["tracks", "show", "lemniscate"], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    out = result.output
    assert "same physical gate as #4" in out and "same physical gate as #1" in out
    rows = [line for line in out.splitlines() if line.startswith("│ ") and line.split("│")[1].strip().isdigit()]
    gate_rows = rows[:6]
    assert [r.split("│")[1].strip() for r in gate_rows] == ["0", "1", "2", "3", "4", "5"]
    # gate 0 at (1.5, 3.5, 0.75), yaw -90 deg, passed towards +y
    cells = [c.strip() for c in gate_rows[0].split("│")[1:-1]]
    assert cells[1:5] == ["1.50", "3.50", "0.75", "-90.0"] and cells[5].startswith("+y")
    assert "obstacles" in out and "arena: x [-2.5, 2.5] y [2, 9] z [0, 3] m" in out
    ct = runner.invoke(app, ["tracks", "show", "complex"], env={"COLUMNS": "200"})
    assert ct.exit_code == 0 and "stacked with #3" in ct.output and "stacked with #2" in ct.output


@pytest.mark.parametrize("obstacles", [False, True])
def test_show_png_writes_a_real_picture(tmp_path, obstacles):
    png = tmp_path / "sub" / "ct.png"
    args = ["tracks", "show", "complex", "--png", str(png)] + (["--obstacles"] if obstacles else [])
    result = runner.invoke(app, args, env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    data = png.read_bytes()
    assert data[:8] == PNG_SIGNATURE and len(data) > 20_000
    import matplotlib.image as mpimg

    img = mpimg.imread(png)
    assert img.shape[0] > 500 and img.shape[1] > 500
    red = (img[..., 0] > 0.75) & (img[..., 1] < 0.3) & (img[..., 2] < 0.3)  # gate openings
    green = (img[..., 1] > 0.5) & (img[..., 0] < 0.35) & (img[..., 2] < 0.35)  # pass-direction arrows
    assert red.sum() > 500 and green.sum() > 200


def test_obstacles_flag_changes_the_picture(tmp_path):
    import matplotlib.image as mpimg

    paths = []
    for flag in ([], ["--obstacles"]):
        p = tmp_path / f"lt{len(flag)}.png"
        assert runner.invoke(app, ["tracks", "show", "lemniscate", "--png", str(p), *flag]).exit_code == 0
        paths.append(p)
    plain, with_obs = (mpimg.imread(p) for p in paths)

    def bluish(img):  # transparent blue obstacle fill over white
        return ((img[..., 2] > 0.8) & (img[..., 0] < 0.85) & (img[..., 0] > 0.5)).sum()

    assert bluish(with_obs) > bluish(plain) + 2000


def test_malformed_track_gives_one_error_line_and_exit_2(tmp_path):
    bad = tmp_path / "bad.yaml"
    text = (TRACKS_DIR / "lemniscate.yaml").read_text().replace("z_max: 3.0", "z_max: 3.0\n  z_min: 0.0")
    bad.write_text(text)
    result = run_cli("tracks", "show", str(bad))
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert lines[0].startswith("error: ") and str(bad) in lines[0] and "arena.z_min" in lines[0]
    assert "Traceback" not in result.stderr + result.stdout


def test_unknown_track_name_gives_exit_2():
    result = run_cli("tracks", "show", "no_such_track")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.count("\n") == 1 and "no such track file" in result.stderr


def test_list_reports_a_broken_track_file_and_still_lists_the_others(tmp_path):
    home = tmp_path / "home"
    shutil.copytree(TRACKS_DIR, home / "tracks")
    (home / "tracks" / "broken.yaml").write_text("name: broken\ngates: [[0, 0, 1, 0]\n")
    result = run_cli("tracks", "list", home=home)
    assert result.returncode == 0, result.stderr
    assert "broken" in result.stdout and "invalid" in result.stdout
    assert "lemniscate" in result.stdout and "complex" in result.stdout


def test_a_track_whose_name_is_not_its_file_name_is_refused_with_one_line(tmp_path):
    """Tracks are found by file name; a file whose `name:` differs would list under one name and be
    found under another (and policies are matched by the name)."""
    home = tmp_path / "home"
    shutil.copytree(TRACKS_DIR, home / "tracks")
    text = (TRACKS_DIR / "lemniscate.yaml").read_text().replace("name: lemniscate", "name: ovalx")
    assert "name: ovalx" in text
    (home / "tracks" / "oval2.yaml").write_text(text)
    result = run_cli("tracks", "show", "oval2", home=home)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.count("\n") == 1 and "'ovalx'" in result.stderr and "'oval2'" in result.stderr
    listed = run_cli("tracks", "list", home=home)
    assert listed.returncode == 0 and "oval2" in listed.stdout and "lemniscate" in listed.stdout


def test_a_gate_whose_opening_reaches_outside_the_arena_is_refused(tmp_path):
    """Only gate centres were checked against the arena's x and y: a narrower arena left gate 2's
    opening beyond the fence (the ceiling was checked against the frame already)."""
    tight = tmp_path / "tight.yaml"
    text = (TRACKS_DIR / "lemniscate.yaml").read_text()
    assert "x: [-2.5, 2.5]" in text
    tight.write_text(text.replace("x: [-2.5, 2.5]", "x: [-2.1, 2.1]"))
    result = run_cli("tracks", "show", str(tight))
    assert result.returncode == 2 and result.stderr.count("\n") == 1, result.stderr
    assert "gates[2]" in result.stderr and "opening reaches (-2.50, 7.00), outside the arena" in result.stderr
