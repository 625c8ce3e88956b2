from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
TESTS = Path(__file__).resolve().parent


@pytest.fixture(autouse=True)
def physint_home(tmp_path, monkeypatch):
    """Every test gets its own physint home."""
    monkeypatch.setenv("PHYSINT_HOME", str(tmp_path / "home"))
    return tmp_path / "home"


@pytest.fixture
def toy_plugins():
    """The process-wide plugin set with the simulator-free toy method added."""
    import toy_plugin

    from physint_cli import plugins

    plugins.reset_plugins()
    p = plugins.get_plugins()
    p.add(toy_plugin, "toy")
    yield p
    plugins.reset_plugins()


def run_cli(*args: str, env: dict | None = None, cwd: Path | None = None, timeout: float = 600) -> subprocess.CompletedProcess:
    """Run the installed `physint` in a subprocess, as a user would."""
    full_env = {**os.environ, **(env or {})}
    return subprocess.run([sys.executable, "-m", "physint_cli", *args], capture_output=True, text=True, env=full_env,
                          cwd=cwd, timeout=timeout)


def call(*args: str) -> tuple[int, str, str]:
    """Run the CLI in-process (so plugins added by fixtures are seen): (exit code, stdout, stderr)."""
    import contextlib
    import io

    from physint_cli import cli

    out, err = io.StringIO(), io.StringIO()
    saved, cli._RESULTS = cli._RESULTS, out
    try:
        with contextlib.redirect_stderr(err):
            code = cli.run(list(args))
    finally:
        cli._RESULTS = saved
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def one_torch_thread():
    """torch on one thread for a test module (floating-point sums in a fixed order), restored after."""
    import torch

    saved = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(saved)

