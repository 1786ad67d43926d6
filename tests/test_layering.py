"""The import layering of ARCHITECTURE.md holds: ``cli``/``commands``/``experiments`` -> task
packages -> ``sim`` -> ``data`` -> ``imu`` -> ``geometry`` -> base modules (the import-linter
contract in ``pyproject.toml``), the experiment scripts never import the CLI's commands, and the
commands never import each other."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_package_imports_follow_the_layers():
    pytest.importorskip("importlinter", reason="import-linter is a dev dependency")
    # A fresh interpreter: import-linter's console keeps the stdout it first saw, which
    # pytest's capture closes between tests.
    script = ("import sys; from importlinter.cli import lint_imports; "
              "sys.exit(lint_imports(config_filename=sys.argv[1], no_cache=True, no_logo=True))")
    done = subprocess.run([sys.executable, "-c", script, os.fspath(ROOT / "pyproject.toml")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr


def _imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=os.fspath(path))):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return names


def test_experiments_do_not_import_commands():
    scripts = sorted((ROOT / "experiments").glob("*.py"))
    assert scripts, "no experiment scripts found"
    offenders = {
        script.name: sorted(m for m in _imported_modules(script)
                            if m == "uavcal_jax.commands" or m.startswith("uavcal_jax.commands."))
        for script in scripts
    }
    offenders = {name: mods for name, mods in offenders.items() if mods}
    assert not offenders, f"experiments import the CLI's commands: {offenders}"


def test_commands_do_not_import_each_other():
    # also the import-linter independence contract; this one runs without the dev dependency
    modules = sorted((ROOT / "uavcal_jax" / "commands").glob("*.py"))
    assert len(modules) > 2, "no command modules found"
    offenders = {
        module.name: sorted(m for m in _imported_modules(module)
                            if m == "uavcal_jax.commands" or m.startswith("uavcal_jax.commands."))
        for module in modules
    }
    offenders = {name: mods for name, mods in offenders.items() if mods}
    assert not offenders, f"commands import other commands: {offenders}"


def test_only_the_plots_module_draws():
    # figures are drawn at the edge (uavcal_jax/plots.py), never in the task packages
    package = ROOT / "uavcal_jax"
    drawing = sorted(str(path.relative_to(package)) for path in package.rglob("*.py")
                     if any(m == "matplotlib" or m.startswith("matplotlib.")
                            for m in _imported_modules(path)))
    assert drawing == ["plots.py"], f"modules importing matplotlib: {drawing}"
