"""A sweep refuses, before any run starts (--dry-run included), what `cfrace train` refuses before its
banner: the command's own option parser and checks (cfrace.rl.train_options.check_train_argv); and it
prints user-given paths, names and addresses as given."""

from __future__ import annotations

from pathlib import Path

import pytest
from typer.testing import CliRunner

from cfrace.cli.main import app, main

DS_FILE = Path(__file__).resolve().parents[1] / "policies" / "ds_lemniscate.onnx"
BASE = "version: 1\nout: {out}\ndefaults: {{preset: cpu, threads: 1, track: lemniscate, steps: 100}}\n"


def _cfrace(capsys, *args) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main(list(args))
    out, err = capsys.readouterr()
    return exc.value.code, out, err


@pytest.mark.parametrize("run, message", [
    ("{name: a, method: ds, minutes: -1}", "runs[0] (a): Invalid value for '--minutes'"),
    ("{name: a, method: ds, envs: 0}", "runs[0] (a): Invalid value for '--envs'"),
    ("{name: a, method: ds, precision: fp16}", "runs[0] (a): --precision 'fp16': choose from auto, fp32, bf16"),
    (f"{{name: a, method: ours, fixed_opponent: '{DS_FILE}', fixed_opponent_frac: 1.5}}",
     "runs[0] (a): --fixed-opponent-frac must be in (0, 1], got 1.5"),
    (f"{{name: a, method: ds, fixed_opponent: '{DS_FILE}'}}",
     "runs[0] (a): --fixed-opponent needs a multi-agent method (ours, dm), not ds"),
    ("{name: a, method: ours, drones: 3, fixed_opponent: a0, fixed_opponent_drones: 3}",
     "runs[0] (a): --fixed-opponent-drones 3: from 1 to 2 with 3 drones per world"),
])
def test_the_sweep_refuses_what_train_refuses(tmp_path, capsys, run, message):
    out = tmp_path / "out"
    p = tmp_path / "s.yaml"
    p.write_text(BASE.format(out=out) + f"runs:\n  - {{name: a0, method: ds}}\n  - {run}\n")
    message = message.replace("runs[0]", "runs[1]")
    for mode in ("--dry-run", "--sequential"):
        code, text, err = _cfrace(capsys, "sweep", str(p), mode)
        assert code == 2 and text == "" and not out.exists(), (mode, text, err)
        assert err.startswith(f"error: {p}: {message}") and err.count("\n") == 1, (mode, err)


def test_a_good_sweep_still_passes(tmp_path, capsys):
    p = tmp_path / "s.yaml"
    p.write_text(BASE.format(out=tmp_path / "out") + "runs:\n  - {name: a, method: ds, precision: fp32}\n"
                 f"  - {{name: b, method: ours, init_from: a, fixed_opponent: '{DS_FILE}', fixed_opponent_frac: 1.0}}\n")
    code, text, err = _cfrace(capsys, "sweep", str(p), "--dry-run")
    assert code in (0, None) and err == "", err


def test_paths_names_and_addresses_print_as_given(tmp_path, monkeypatch):
    """[b] is no markup and :abc: no emoji code, in the dry run's commands and the Ray title."""
    import cfrace.sweep.ray_exec as ray_exec

    folder = tmp_path / "x[b]y"
    folder.mkdir()
    p = folder / "[b]sw.yaml"
    p.write_text(BASE.format(out=f"'{folder}/o:abc:t'") + "runs:\n  - {name: 'r[b]', method: ds}\n")
    res = CliRunner().invoke(app, ["sweep", str(p), "--dry-run"], env={"COLUMNS": "400"})
    assert res.exit_code == 0, res.output
    assert res.output.splitlines()[0] == "r[b] (new; after nothing)", res.output
    assert f"--out '{folder}/o:abc:t/r[b]'" in res.output, res.output

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(ray_exec, "require_ray", lambda: None)
    monkeypatch.setattr(ray_exec, "run_ray", stopped)
    res = CliRunner().invoke(app, ["sweep", str(p), "--address", "nohost:abc"], env={"COLUMNS": "400"})
    assert res.exit_code == 130, res.output
    assert f"sweep {p} -> {folder}/o:abc:t on nohost:abc: 1 runs" in " ".join(res.output.split()), res.output
