"""The package's layout holds: layers and acyclic modules (import-linter's contracts in pyproject.toml),
no module forwarding names that moved, short modules, the source where it installs, no import-time settings."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT

pytestmark = pytest.mark.fast

PACKAGE = ROOT / "stablebptt"
MAX_LINES = 450  # a module a reader holds in mind at once
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"


def _modules() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def test_import_contracts_hold():
    result = subprocess.run([str(LINT_IMPORTS), "--config", str(ROOT / "pyproject.toml"), "--no-cache"], cwd=ROOT,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "2 kept, 0 broken" in result.stdout


def test_import_contracts_catch_a_circle(tmp_path):
    """The contracts fail where one module of a package imports a sibling that imports it back."""
    package = tmp_path / "circular"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("from circular import b\n")
    (package / "b.py").write_text("def f():\n    from circular import a  # inside a function: still an arrow\n")
    config = tmp_path / "contracts.toml"
    config.write_text('[tool.importlinter]\nroot_package = "circular"\n\n[[tool.importlinter.contracts]]\n'
                      'name = "acyclic"\ntype = "acyclic_siblings"\nancestors = ["circular"]\n')
    result = subprocess.run([str(LINT_IMPORTS), "--config", str(config), "--no-cache"], cwd=tmp_path,
                            capture_output=True, text=True, timeout=300, env={"PYTHONPATH": str(tmp_path)})
    assert result.returncode == 1 and "BROKEN" in result.stdout, result.stdout + result.stderr


def test_no_module_forwards_names_through_a_module_getattr():
    # The package's face alone defines one: env_task is imported on first use (MuJoCo must not load
    # before a renderer has chosen its OpenGL backend).
    forwarding = [path.relative_to(ROOT).as_posix() for path in _modules()
                  if any(isinstance(node, ast.FunctionDef) and node.name == "__getattr__"
                         for node in ast.parse(path.read_text()).body)]
    assert forwarding == ["stablebptt/__init__.py"]


def test_every_module_is_short():
    long = {path.relative_to(ROOT).as_posix(): lines for path in _modules()
            if (lines := len(path.read_text().splitlines())) > MAX_LINES}
    assert long == {}



def test_the_source_sits_where_it_installs():
    assert "package-dir" not in (ROOT / "pyproject.toml").read_text()
    for folder in ("tasks", "models", "commands"):
        assert (PACKAGE / folder / "__init__.py").is_file()
        assert not (ROOT / folder).exists()
    scripts = sorted(path.stem for path in (ROOT / "scripts").glob("*.py"))
    assert scripts == sorted(path.stem for path in (PACKAGE / "commands").glob("*.py")
                             if path.stem not in ("__init__", "main", "task_options"))


def test_every_record_under_results_is_cited_by_a_document():
    """results/ keeps what the documents cite (a file, or a folder holding it), in a tree a reader can
    take in; history stays in git (results/LOG.md says where)."""
    listed = subprocess.run(["git", "ls-files", "results"], cwd=ROOT, capture_output=True, text=True)
    if listed.returncode != 0:
        pytest.skip("not a git checkout: the committed records are git's files")
    records = listed.stdout.split()
    documents = [ROOT / "README.md", *(ROOT / "docs").glob("*.md"), *PACKAGE.rglob("*.py"), *PACKAGE.rglob("*.md"),
                 *(ROOT / "benchmarks").rglob("*.py")]
    text = "\n".join(path.read_text() for path in documents)
    uncited = [record for record in records
               if not any(folder in text for folder in ("/".join(record.split("/")[:depth])
                                                        for depth in range(2, record.count("/") + 2)))]
    assert uncited == []
    assert len(records) <= 120
