"""`cfrace bench train --compare`: two training configurations timed side by side in one run.

A configuration is this working tree with some `bench train` options changed (``precision=fp32``,
``threads=2,envs=2048``), or a git revision of this repository (``main``, ``d39f681``): that
revision is checked out into a temporary git worktree and timed with its own code. Each
configuration runs in a fresh subprocess (`cfrace bench train --json`), alternating A B A B ...,
so that slow phases of a shared machine hit both; the figures are the medians over the rounds and
the result is the ratio A / B (with A this tree as given on the command line: its speed-up over B).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

from cfrace.errors import ConfigError

#: `bench train` options a comparison may change, with their command-line flag
OPTIONS = {"precision": "--precision", "threads": "--threads", "envs": "--envs", "preset": "--preset",
           "method": "--method", "track": "--track", "iterations": "--iterations", "device": "--device",
           "update_workers": "--update-workers", "compile": "--compile"}
#: on/off options: KEY=true gives the flag, KEY=false its --no- form
SWITCHES = ("compile",)
#: figures compared; env_steps_per_cpu_s (steps per CPU second of the process) is the one that other
#: processes on a shared machine hardly change
FIGURES = ("env_steps_per_s", "env_steps_per_cpu_s", "iteration_s", "share_update", "share_sim", "share_inference")


@dataclass(frozen=True)
class Config:
    label: str                       #: what the table calls it
    options: dict = field(default_factory=dict)   #: bench train options (OPTIONS keys)
    rev: str | None = None           #: a git revision; None = this working tree


def parse_compare(text: str, base: dict) -> Config:
    """``KEY=VALUE[,KEY=VALUE...]`` (options over ``base``) or a git revision."""
    text = text.strip()
    if not text:
        raise ConfigError("--compare: give options (e.g. precision=fp32) or a git revision (e.g. main)")
    if "=" not in text:
        return Config(f"rev {text}", dict(base), rev=text)
    opts = dict(base)
    for item in text.split(","):
        key, _, value = item.partition("=")
        key = key.strip().replace("-", "_")
        if key not in OPTIONS or not value.strip():
            raise ConfigError(f"--compare {item!r}: expected KEY=VALUE with KEY one of {', '.join(OPTIONS)}")
        opts[key] = value.strip()
    return Config(text, opts)


#: options that came after --compare: a revision knows one when its `bench train` command lists the flag
LATE = ("precision", "update_workers", "compile")


def rev_knows(rev: str, option: str) -> bool:
    """Whether `bench train` at ``rev`` takes ``option``."""
    if option not in LATE:
        return True
    proc = subprocess.run(["git", "-C", str(repo_root()), "show", f"{rev}:cfrace/cli/train.py"],
                          capture_output=True, text=True)
    return proc.returncode == 0 and f'"{OPTIONS[option]}' in proc.stdout


def repo_root() -> Path:
    """The git checkout this cfrace is imported from."""
    here = Path(__file__).resolve().parents[2]
    try:
        out = subprocess.run(["git", "-C", str(here), "rev-parse", "--show-toplevel"], capture_output=True,
                             text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        raise ConfigError(f"--compare REV needs cfrace imported from a git checkout (this one: {here})") from None
    return Path(out)


@contextmanager
def checkout(rev: str | None):
    """Yield the source folder of a configuration: this tree, or ``rev`` in a temporary worktree."""
    if rev is None:
        yield Path(__file__).resolve().parents[2]
        return
    root = repo_root()
    ok = subprocess.run(["git", "-C", str(root), "rev-parse", "--verify", "--quiet", f"{rev}^{{commit}}"],
                        capture_output=True, text=True)
    if ok.returncode != 0:
        raise ConfigError(f"--compare {rev!r}: not a git revision of {root} (nor KEY=VALUE options)")
    tmp = Path(tempfile.mkdtemp(prefix="cfrace-compare-"))
    path = tmp / "tree"
    subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", "--quiet", str(path), rev], check=True,
                   capture_output=True)
    try:
        yield path
    finally:
        subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force", str(path)], capture_output=True)


def run_once(source: Path, options: dict, overrides: list[str]) -> dict:
    """One `cfrace bench train --json` in a subprocess importing cfrace from ``source``."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "bench.json"
        # through the entry function (older revisions have no `python -m cfrace.cli.main`)
        cmd = [sys.executable, "-c", "import sys; from cfrace.cli.main import main; sys.argv[0] = 'cfrace'; main()",
               "bench", "train", "--json", str(out)]
        for key, value in options.items():
            if key in SWITCHES and value is not None:
                on = str(value).lower() in ("true", "1", "yes", "on")
                cmd.append(OPTIONS[key] if on else "--no-" + OPTIONS[key][2:])
            elif value is not None:
                cmd += [OPTIONS[key], str(value)]
        for item in overrides:
            cmd += ["--set", item]
        env = {**os.environ, "PYTHONPATH": str(source)}
        proc = subprocess.run(cmd, cwd=source, env=env, capture_output=True, text=True)
        if proc.returncode != 0 or not out.exists():
            last = (proc.stderr.strip() or proc.stdout.strip()).splitlines()[-1:] or ["(no output)"]
            raise ConfigError(f"bench train failed in {source} ({' '.join(cmd[5:])}): {last[0]}")
        return json.loads(out.read_text())


def compare(a: Config, b: Config, overrides: list[str] = (), rounds: int = 2, on_result=None) -> dict:
    """Time A and B alternately ``rounds`` times each; medians and ratios A / B."""
    runs: dict[str, list[dict]] = {"a": [], "b": []}
    with checkout(a.rev) as src_a, checkout(b.rev) as src_b:
        for r in range(rounds):
            for key, cfg, src in (("a", a, src_a), ("b", b, src_b)):
                res = run_once(src, cfg.options, list(overrides))
                runs[key].append(res)
                if on_result is not None:
                    on_result(r, cfg, res)
    # an older revision may lack a figure (env_steps_per_cpu_s): None there
    med = {k: {f: statistics.median(x[f] for x in v) if all(f in x for x in v) else None for f in FIGURES}
           for k, v in runs.items()}
    ratio = {f: (med["a"][f] / med["b"][f]) if med["a"][f] is not None and med["b"][f] else None for f in FIGURES}
    return {"a": {"label": a.label, "options": a.options, "rev": a.rev, "median": med["a"], "runs": runs["a"],
                  "precision": runs["a"][-1].get("precision")},
            "b": {"label": b.label, "options": b.options, "rev": b.rev, "median": med["b"], "runs": runs["b"],
                  "precision": runs["b"][-1].get("precision")},
            "ratio_a_over_b": ratio, "rounds": rounds}
