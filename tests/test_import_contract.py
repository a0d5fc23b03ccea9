"""The import contract (``.importlinter``, run by ``make lint``) holds on the tree, and it
would catch what it is there for: an upward import made inside a function, and a circle
between two modules of one package."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LINT = str(Path(sys.executable).parent / "lint-imports")
FLOORS = ("mapping", "planning", "drivers", "daemon", "seamap", "tools")


def _lint(root: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(root)}
    return subprocess.run(
        [LINT, str(root / ".importlinter"), "--no-cache"],
        cwd=root, env=env, capture_output=True, text=True, timeout=300,
    )  # fmt: skip


def test_the_tree_keeps_the_contract() -> None:
    done = _lint(REPO)
    assert done.returncode == 0, done.stdout + done.stderr
    assert done.stdout.count("KEPT") == 2


def test_an_upward_import_inside_a_function_and_a_circle_are_caught(tmp_path: Path) -> None:
    shutil.copy(REPO / ".importlinter", tmp_path / ".importlinter")
    for floor in FLOORS:
        (tmp_path / floor).mkdir()
        (tmp_path / floor / "__init__.py").write_text("")
    # The core reaching for the simulator, lazily, as the product once did.
    (tmp_path / "mapping" / "core.py").write_text("def f():\n    import tools.sim\n")
    (tmp_path / "tools" / "sim.py").write_text("")
    # Two driver modules that import each other, one only for a type.
    (tmp_path / "drivers" / "ping.py").write_text("import drivers.protocol\n")
    (tmp_path / "drivers" / "protocol.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    import drivers.ping\n"
    )
    done = _lint(tmp_path)
    assert done.returncode != 0
    assert "mapping is not allowed to import tools" in done.stdout, done.stdout
    assert "No cycles are allowed in drivers" in done.stdout, done.stdout
