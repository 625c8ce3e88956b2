"""The import layers of DESIGN.md, as contracts: plugins -> backends -> core, the core imports no
simulator, no plugin imports another or a plugin's train module (pyproject.toml's import-linter
contracts), and no module imports one that imports it back, also lazily inside a function."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("physint_cli", "physint_backends", "physint_plugins")


def test_the_import_contracts_in_pyproject_are_kept():
    lint = Path(sys.executable).with_name("lint-imports")
    done = subprocess.run([str(lint), "--config", str(ROOT / "pyproject.toml"), "--no-cache"], capture_output=True,
                          text=True, cwd=ROOT, timeout=300)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert "4 kept, 0 broken" in done.stdout


def import_cycles(*packages: str) -> list[tuple[str, str]]:
    """Every import ``a -> b`` (function-level imports included) from which ``b`` leads back to ``a``."""
    import grimp

    graph = grimp.build_graph(*packages)
    return sorted({tuple(sorted((a, b))) for a in graph.modules for b in graph.find_modules_directly_imported_by(a)
                   if graph.chain_exists(importer=b, imported=a)})


def test_no_module_imports_one_that_imports_it_back():
    assert import_cycles(*PACKAGES) == []


def test_the_cycle_check_finds_a_cycle(tmp_path, monkeypatch):
    package = tmp_path / "loop"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "a.py").write_text("def f():\n    from . import b\n")  # lazily, inside a function
    (package / "b.py").write_text("from . import a\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert import_cycles("loop") == [("loop.a", "loop.b")]
