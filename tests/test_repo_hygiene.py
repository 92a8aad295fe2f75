"""The repository's hygiene: no pointers to files outside it, no test that imports a benchmark script
or a study or runs one (but the listed maintained examples), and every result file in git cited by a doc."""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SKIP = {".git", ".venv", "__pycache__", "node_modules"}
OFF_REPO = re.compile(r"facts\.md|design\.md|design notes|\.\./shared", re.IGNORECASE)


def repo_files(*suffixes: str) -> list[Path]:
    """Files of the repository (not the virtualenv or git's own) whose name ends in one of suffixes."""
    return [p for p in REPO.rglob("*") if p.is_file() and p.suffix in suffixes
            and not SKIP.intersection(p.relative_to(REPO).parts)]


def test_no_file_cites_a_file_outside_the_repository():
    this = Path(__file__).resolve()
    found = [f"{p.relative_to(REPO)}:{n}: {line.strip()}"
             for p in repo_files(".py", ".md", ".yaml", ".yml") if p.resolve() != this
             for n, line in enumerate(p.read_text(errors="replace").splitlines(), 1)
             if OFF_REPO.search(line)]
    assert not found, "off-repository citations:\n" + "\n".join(found)


RESULT_DIRS = ("benchmarks/results", "studies")
RESULT_SUFFIXES = (".json", ".csv", ".txt")
CITED = re.compile(r"[\w{},*.-]+\.(?:json|csv|txt)")


def expand_braces(pattern: str) -> list[str]:
    """'a_{x,y}.json' -> ['a_x.json', 'a_y.json'] (nested braces expand innermost first)."""
    m = re.search(r"\{([^{}]*)\}", pattern)
    if not m:
        return [pattern]
    return [out for alt in m.group(1).split(",")
            for out in expand_braces(pattern[:m.start()] + alt + pattern[m.end():])]


def cited_names(text: str) -> list[str]:
    """The file names and shell-style patterns ('x_*.json', 'x_{a,b}.json') a text cites."""
    return [name.rsplit("/", 1)[-1] for token in CITED.findall(text) for name in expand_braces(token)]


def test_cited_names_expand_braces_and_keep_globs():
    assert cited_names("see `results/a_{x,y_{1,2}}.json` and b_*.csv.") == [
        "a_x.json", "a_y_1.json", "a_x.json", "a_y_2.json", "b_*.csv"]


def test_every_result_file_is_cited_by_a_doc():
    from fnmatch import fnmatch

    docs = [p for p in repo_files(".md") if "tests" not in p.relative_to(REPO).parts]
    patterns = {n for p in docs for n in cited_names(p.read_text(errors="replace"))}
    results = [p for d in RESULT_DIRS if (REPO / d).is_dir() for p in (REPO / d).rglob("*")
               if p.suffix in RESULT_SUFFIXES and p.is_file()]
    uncited = [str(p.relative_to(REPO)) for p in results if not any(fnmatch(p.name, pat) for pat in patterns)]
    assert not uncited, "result files no doc cites:\n" + "\n".join(sorted(uncited))


IMPORTS_A_SCRIPT = re.compile(
    r"spec_from_file_location|exec_module|runpy|import_module"           # loading a file as a module
    r"|sys\.path\.(?:insert|append)\(.*(?:benchmarks|studies|parents)"     # putting the scripts on the path
    r"|^\s*(?:from|import)\s+(?:benchmarks|studies)\b"                     # importing them as packages
    r"|[\"']studies[\"']", re.MULTILINE)                                    # a path into studies/


def test_no_test_imports_a_benchmark_script_or_a_study():
    """Tests call what they check in cfrace/; a maintained example listed in MAINTAINED_EXAMPLES may be run
    as a user runs it (a subprocess), a study not at all."""
    this = Path(__file__).resolve()
    found = [f"{p.relative_to(REPO)}: {m.group(0).strip()}" for p in (REPO / "tests").rglob("*.py")
             if p.resolve() != this for m in IMPORTS_A_SCRIPT.finditer(p.read_text())]
    assert not found, "tests that import scripts:\n" + "\n".join(found)


#: tests that run a benchmarks/ script as its users do (a subprocess), each with its reason; no test runs a study
MAINTAINED_EXAMPLES = {
    "tests/test_example_skrl.py": "benchmarks/train_skrl_ppo.py is the documented example of a third-party "
                                  "trainer (skrl's PPO) on cfrace's Gymnasium vector env: what it shows is the "
                                  "script itself, so the test runs it as a user does",
}


def script_dirs_named(source: str) -> list[str]:
    """The string constants of a Python source, docstrings left out, that name benchmarks/ or studies/
    (a path to a script there, as a test that runs one must build)."""
    import ast

    tree = ast.parse(source)
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))
                  and node.body and isinstance(node.body[0], ast.Expr) and isinstance(node.body[0].value, ast.Constant)}
    return [node.value for node in ast.walk(tree) if isinstance(node, ast.Constant) and isinstance(node.value, str)
            and id(node) not in docstrings and re.search(r"(^|/)(benchmarks|studies)(/|$)", node.value)]


def test_script_dirs_named_sees_paths_and_not_docstrings():
    src = '"""benchmarks/x.py prints it."""\ndef f():\n    """studies/y.py"""\n    return ROOT / "benchmarks" / "x.py", "studies/y.py", "benchmarks_like"\n'
    assert sorted(script_dirs_named(src)) == ["benchmarks", "studies/y.py"]


def test_no_test_runs_a_script_but_the_maintained_examples():
    named = {str(p.relative_to(REPO)): script_dirs_named(p.read_text()) for p in sorted((REPO / "tests").rglob("*.py"))
             if p.resolve() != Path(__file__).resolve()}
    found = {f: names for f, names in named.items() if names and f not in MAINTAINED_EXAMPLES}
    assert not found, f"tests that run a benchmarks/ or studies/ script (call cfrace/ instead): {found}"
    stale = [f for f in MAINTAINED_EXAMPLES if not named.get(f)]
    assert not stale, f"listed as running a maintained example but no longer do: {stale}"
    assert not any("studies" in n for f in MAINTAINED_EXAMPLES for n in named.get(f, [])), "a study is no example"
