"""`cfrace bench sim` refuses bad input with one line before it prints anything (the machine banner),
and a run in which no requested mode could measure anything is an error, not an empty table."""

from __future__ import annotations

import pytest

from cfrace.cli.main import main
from cfrace.sim import ckernel
from cfrace.sim import throughput as bench


def _cfrace(capsys, *args) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as exc:
        main(list(args))
    out, err = capsys.readouterr()
    return exc.value.code, out, err


@pytest.mark.parametrize("args, message", [
    (["--modes", "cc"], "--modes: expected a subset of c,eager,compiled, got 'cc'"),
    (["--scenario", "gate"], "unknown scenario 'gate' (known: hover, gates)"),
    (["--track", "complexx"], ""),
    (["--drones", "17", "--modes", "c"], "--modes c: the C kernel takes at most 16 drones per world, not --drones 17"),
])
def test_bad_input_is_one_line_before_anything_is_printed(capsys, args, message):
    code, out, err = _cfrace(capsys, "bench", "sim", "--worlds", "2", "--no-peer", *args)
    assert code == 2 and out == "", out
    assert err.startswith(f"error: {message}") and err.count("\n") == 1, err


def test_more_drones_than_the_kernel_takes_default_to_eager():
    assert "c" not in bench.choose_modes(False, drones=ckernel.MAX_DRONES + 1)
    assert bench.choose_modes(False, drones=2) == bench.available_modes(False)


def test_no_mode_that_ran_is_an_error(capsys, monkeypatch):
    def failing(*args, **kwargs):
        raise RuntimeError("no compiler")

    monkeypatch.setattr(bench, "measure_sim", failing)
    monkeypatch.setattr(bench, "choose_modes", lambda *a, **k: ["compiled"])
    code, out, err = _cfrace(capsys, "bench", "sim", "--worlds", "2", "--no-peer", "--steps", "1", "--repeats", "1")
    assert code == 2 and err == "error: no mode could run: compiled: RuntimeError: no compiler\n", err
    assert "worlds" not in out.split("unavailable")[-1], out     # no empty table
