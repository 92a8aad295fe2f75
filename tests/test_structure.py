"""The package's structure: no import cycles, ordered layers, no torch on the `fly` path, one policy contract,
no folder of more than 16 modules."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np

import cfrace

ROOT = Path(cfrace.__file__).parent


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph() -> dict[str, set[str]]:
    """cfrace module -> the cfrace modules it imports, at module level or inside functions."""
    files = {_module_name(p): p for p in ROOT.rglob("*.py")}
    graph: dict[str, set[str]] = {m: set() for m in files}
    for mod, path in files.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                names = [base] + [f"{base}.{a.name}" for a in node.names]
            else:
                continue
            graph[mod] |= {n for n in names if n in files and n != mod}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import cycle as [a, b, ..., a], or None (depth-first search)."""
    state: dict[str, int] = {}   # 1 on the stack, 2 done
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 1:
                return stack[stack.index(n):] + [n]
            if n not in state and (found := visit(n)):
                return found
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(graph):
        if m not in state and (found := visit(m)):
            return found
    return None


def test_the_cycle_finder_finds_a_cycle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_the_import_graph_sees_function_level_and_relative_imports():
    graph = import_graph()
    assert "cfrace.flight.link.crazyflie" in graph["cfrace.flight.link.opener"]   # imported inside open_link
    assert "cfrace.contract" in graph["cfrace.policy"]


def test_no_import_cycles_in_cfrace():
    assert find_cycle(import_graph()) is None


#: docs/architecture.md's layers, lowest first: every cfrace package (a subpackage of cfrace, or a module
#: directly in it) lies in exactly one, and imports only its own layer and those below
LAYERS = [
    ("foundation", ["cfrace", "cfrace.errors", "cfrace.paths", "cfrace.yamlcfg", "cfrace.arrays", "cfrace.rotations",
                    "cfrace.drone", "cfrace.track", "cfrace.trackplot", "cfrace.loopmodel"]),
    ("simulation model", ["cfrace.sim"]),
    ("policy contract", ["cfrace.contract"]),
    ("policy files", ["cfrace.policy", "cfrace.policygraph"]),
    ("environment", ["cfrace.env"]),
    ("training and export", ["cfrace.rl", "cfrace.export"]),
    ("simulated Crazyflie", ["cfrace.simcf"]),
    ("flight stack", ["cfrace.flight"]),
    ("thrust-stand calibration", ["cfrace.calibrate"]),
    ("rehearsal", ["cfrace.rehearsal"]),
    ("sweeps", ["cfrace.sweep"]),
    ("evaluation", ["cfrace.evaluate"]),
    ("reproduction", ["cfrace.reproduction"]),
    ("CLI", ["cfrace.cli", "cfrace.__main__"]),
]


def package_of(module: str) -> str:
    """The cfrace package a module belongs to: cfrace.X for cfrace.X and everything under it."""
    return ".".join(module.split(".")[:2])


def package_graph(graph: dict[str, set[str]]) -> dict[str, set[str]]:
    """cfrace package -> the other cfrace packages its modules import."""
    out: dict[str, set[str]] = {package_of(m): set() for m in graph}
    for a, deps in graph.items():
        out[package_of(a)] |= {package_of(b) for b in deps} - {package_of(a)}
    return out


def layer_of(module: str) -> int:
    """The index in LAYERS of the layer holding ``module``'s package (KeyError if none does)."""
    for k, (_, packages) in enumerate(LAYERS):
        if package_of(module) in packages:
            return k
    raise KeyError(f"{package_of(module)} is in no layer of LAYERS (docs/architecture.md)")


def test_every_package_lies_in_exactly_one_layer():
    listed = [p for _, packages in LAYERS for p in packages]
    assert len(listed) == len(set(listed)), "a package is listed in two layers"
    assert set(package_graph(import_graph())) == set(listed)


def test_the_package_graph_sees_a_cycle_between_packages_that_modules_alone_do_not():
    modules = {"cfrace.a.x": {"cfrace.b.y"}, "cfrace.b.y": set(), "cfrace.b.z": {"cfrace.a.w"}, "cfrace.a.w": set()}
    assert find_cycle(modules) is None
    assert find_cycle(package_graph(modules)) == ["cfrace.a", "cfrace.b", "cfrace.a"]


def test_no_import_cycles_between_packages():
    assert find_cycle(package_graph(import_graph())) is None


def test_every_module_imports_only_its_layer_and_those_below():
    graph = import_graph()
    up = sorted((a, b) for a, deps in graph.items() for b in deps
                if layer_of(b) > layer_of(a))
    assert not up, "imports up the layers: " + ", ".join(f"{a} ({LAYERS[layer_of(a)][0]}) -> {b} "
                                                         f"({LAYERS[layer_of(b)][0]})" for a, b in up)


def _modules_loaded_by(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys; print('\\n'.join(sys.modules))"],
                         capture_output=True, text=True, check=True).stdout
    return set(out.split())


FLY_PATH = ["cfrace.cli.flight", "cfrace.flight.loop.flight_loop", "cfrace.flight.loop.race", "cfrace.flight.link.opener",
            "cfrace.flight.link.crazyflie", "cfrace.flight.mocap.sources", "cfrace.flight.mocap.estimation", "cfrace.flight.safety.check",
            "cfrace.flight.loop.gate_progress", "cfrace.flight.log.writer", "cfrace.flight.config", "cfrace.policy",
            "cfrace.contract", "cfrace.contract.observations", "cfrace.contract.actions"]


def test_the_fly_path_imports_no_torch():
    loaded = _modules_loaded_by("\n".join(f"import {m}" for m in FLY_PATH))
    assert set(FLY_PATH) <= loaded
    assert "torch" not in loaded, "a module on the fly path imports torch at module level"


def test_the_policy_contract_imports_neither_torch_nor_the_trainer():
    loaded = _modules_loaded_by("import cfrace.contract, cfrace.policy")
    assert "torch" not in loaded and not any(m.startswith("cfrace.rl") for m in loaded)


def test_the_gate_rule_is_defined_once():
    """kernel.c takes the gate rule's constants from cfrace.sim.gates (as build flags: ckernel's
    rule_defines) instead of literals of its own; the flight stack imports them from there too."""
    import re

    from cfrace.sim import ckernel, gates

    src = (ROOT / "sim" / "kernel.c").read_text()
    for literal in ("1.0f", "0.5f", "0.4f"):
        assert not re.search(rf"(<|>=)\s*{re.escape(literal)}", src), f"kernel.c compares against {literal}"
    for name in ("PASS_RADIUS", "PASS_HALF", "FRAME_HIT_HALF"):
        assert re.search(rf"(<|>=)\s*{name}\b", src), f"kernel.c does not use {name}"
    rule = {"PASS_RADIUS": gates.PASS_RADIUS, "PASS_HALF": gates.PASS_HALF, "FRAME_HIT_HALF": gates.FRAME_HIT_HALF}
    flags = dict(f[2:].split("=") for f in ckernel.rule_defines())
    assert {k: float(v.rstrip("f")) for k, v in flags.items()} == rule
    for path in ROOT.rglob("*.py"):
        if path.name != "gates.py":
            assert not re.search(r"^(PASS_HALF|PASS_RADIUS|FRAME_HIT_HALF)\s*=", path.read_text(), re.M), path


#: files over 400 lines and functions over 60 lines that stay so, each with its reason
LONG_FILES = {
    "sim/kernel.c": "one fused C kernel: its blocks share the lane layout and must be read together",
    "simcf/firmware.py": "SimFleet, the one object every simulated drone's CRTP handler enters under its lock: "
                         "setpoint priorities, watchdogs, arming, params and log values share its per-drone "
                         "firmware state (the controller, planner, estimator and packets have files of their own)",
    "simcf/crtp.py": "CrtpEndpoint, one short handler per CRTP port the firmware serves (link, platform, param, "
                     "log, memory, commander, generic setpoints, high-level, supervisor, localization) and the TOCs",
}
LONG_FUNCTIONS = {
    # typer command signatures: one parameter per option, with its help; the bodies are short
    "cli/flight.py:register": "holds the `fly` command (defined inside it): its option list",
    "cli/flight.py:fly_cmd": "the `fly` command's option list; the body resolves the config and calls fly",
    "cli/sim.py:dry_run_cmd": "the `sim dry-run` command's option list; the body calls dry_run",
    "rl/train_options.py:train_parameters": "the `train` command's option list (the body returns them)",
    "sim/simulator.py:_substep": "the torch reference of one physics step, kept in kernel.c's order to compare them",
}


def test_no_long_files_or_functions_beyond_the_justified_ones():
    long_files, long_functions = set(), set()
    for path in sorted(ROOT.rglob("*")):
        if path.suffix not in (".py", ".c"):
            continue
        rel, text = path.relative_to(ROOT).as_posix(), path.read_text()
        if len(text.splitlines()) > 400:
            long_files.add(rel)
        if path.suffix == ".py":
            for node in ast.walk(ast.parse(text)):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and \
                        node.end_lineno - node.lineno + 1 > 60:
                    long_functions.add(f"{rel}:{node.name}")
    assert long_files <= set(LONG_FILES), f"files over 400 lines: {sorted(long_files - set(LONG_FILES))}"
    assert long_functions <= set(LONG_FUNCTIONS), \
        f"functions over 60 lines: {sorted(long_functions - set(LONG_FUNCTIONS))}"
    # an exception that no longer applies is dropped from the list, so that the list stays what is long
    assert set(LONG_FILES) <= long_files, f"no longer over 400 lines: {sorted(set(LONG_FILES) - long_files)}"
    assert set(LONG_FUNCTIONS) <= long_functions, \
        f"no longer over 60 lines: {sorted(set(LONG_FUNCTIONS) - long_functions)}"


#: the most Python files one folder of the repository may hold (docs/architecture.md): a folder that outgrows
#: it is split by concern, as flight/ was
MAX_MODULES_PER_FOLDER = 16
#: top-level folders whose Python files are not counted, each with its reason
NOT_COUNTED = {"tests": "pytest's test files, one per concern, found by their names",
               "runs": "training and sweep output (git-ignored), not code"}


def module_trees() -> list[Path]:
    """The repository's top-level folders of Python files that the folder rule covers (cfrace/ and the scripts)."""
    return sorted(d for d in ROOT.parent.iterdir() if d.is_dir() and not d.name.startswith((".", "_"))
                  and d.name not in NOT_COUNTED and not d.name.endswith(".egg-info") and any(d.rglob("*.py")))


def modules_per_folder(top: Path) -> dict[str, int]:
    """Each folder under ``top`` (``top`` included) that holds Python files -> how many lie directly in it."""
    folders = [top, *(d for d in top.rglob("*") if d.is_dir() and "__pycache__" not in d.parts)]
    counts = {d: sum(1 for f in d.glob("*.py") if f.is_file()) for d in folders}
    return {d.relative_to(top.parent).as_posix(): n for d, n in counts.items() if n}


def test_modules_per_folder_counts_each_folder_alone(tmp_path):
    for k in range(3):
        (tmp_path / "top" / "sub").mkdir(parents=True, exist_ok=True)
        (tmp_path / "top" / f"m{k}.py").write_text("")
        (tmp_path / "top" / "sub" / f"s{k}.py").write_text("")
    (tmp_path / "top" / "sub" / "notes.md").write_text("")
    (tmp_path / "top" / "empty").mkdir()
    assert modules_per_folder(tmp_path / "top") == {"top": 3, "top/sub": 3}


def test_no_folder_holds_more_than_16_modules():
    trees = module_trees()
    assert ROOT in trees and len(trees) >= 3          # the package and the two folders of scripts
    counts = {k: n for top in trees for k, n in modules_per_folder(top).items()}
    assert {"cfrace", "cfrace/flight/loop"} <= set(counts)
    big = {k: n for k, n in sorted(counts.items()) if n > MAX_MODULES_PER_FOLDER}
    assert not big, f"folders of more than {MAX_MODULES_PER_FOLDER} Python files (split them by concern): {big}"


def test_the_readme_status_is_short():
    """The README's status section is at most 15 lines (history goes to CHANGELOG.md)."""
    text = (ROOT.parent / "README.md").read_text()
    status = text.split("## Status", 1)[1].split("\n## ", 1)[0].strip().splitlines()[1:]
    assert 0 < len([line for line in status if line.strip()]) <= 15, status
