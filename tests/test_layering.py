"""The layers point one way: data knows no algorithm or environment; the library never imports a script;
the benchmarks never import the reproduction study (the study may import the benchmarks)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "torchrl_tels"

#: package -> the torchrl_tels packages it must never import
FORBIDDEN = {
    "data": ("envs", "modules", "objectives", "collection", "diagnostics", "training", "config", "record"),
    "modules": ("objectives", "collection", "training", "config", "record"),
    "objectives": ("collection", "training", "config", "record"),
    "envs": ("objectives", "collection", "training"),
}


def imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_layer_imports_point_one_way(layer):
    offenders = []
    for path in sorted((PACKAGE / layer).rglob("*.py")):
        for name in imported_modules(path):
            parts = name.split(".")
            if parts[0] == "torchrl_tels" and len(parts) > 1 and parts[1] in FORBIDDEN[layer]:
                offenders.append(f"{path.relative_to(PACKAGE.parent)} imports {name}")
    assert not offenders, "\n".join(offenders)


def test_library_never_imports_a_script():
    offenders = [f"{path.relative_to(PACKAGE.parent)} imports {name}"
                 for path in sorted(PACKAGE.rglob("*.py")) for name in imported_modules(path)
                 if name.split(".")[0] in ("recipes", "benchmarks", "study", "tests", "scripts")]
    assert not offenders, "\n".join(offenders)


def test_benchmarks_never_import_the_study():
    offenders = [f"{path.relative_to(REPO)} imports {name}"
                 for path in sorted((REPO / "benchmarks").rglob("*.py")) for name in imported_modules(path)
                 if name.split(".")[0] == "study"]
    assert not offenders, "\n".join(offenders)


def test_tasks_resolve_without_importing_env_modules_by_hand():
    import subprocess
    import sys

    code = "from torchrl_tels.envs import get_task; print(get_task('pointmass-goal').env_id)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "torchrl_tels/PointMassGoal-v0"
