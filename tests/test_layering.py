"""The layers point one way: data knows no algorithm or environment; the library never imports a script;
every name a module exports exists there; the benchmarks never import the reproduction study (the study may
import the benchmarks)."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "torchrl_tels"

#: package -> the torchrl_tels packages it must never import
FORBIDDEN = {
    "data": ("envs", "modules", "objectives", "collection", "diagnostics", "training", "config", "record", "monitor"),
    "modules": ("objectives", "collection", "training", "config", "record", "monitor"),
    "objectives": ("collection", "training", "config", "record"),
    "envs": ("objectives", "collection", "training"),
    "monitor": ("objectives", "collection", "training", "record"),
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


def bound_names(tree: ast.Module) -> set[str]:
    """Names a module binds at its top level (definitions, assignments, imports)."""
    names = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(target.id for target in targets if isinstance(target, ast.Name))
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            names.update((alias.asname or alias.name).split(".")[0] for alias in node.names)
    return names


def test_every_exported_name_is_bound():
    # a name left in __all__ after it moved breaks `from module import *` with an AttributeError
    stale = []
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text())
        for node in tree.body:
            if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
                stale += [f"{path.relative_to(PACKAGE.parent)}: {name}"
                          for name in ast.literal_eval(node.value) if name not in bound_names(tree)]
    assert not stale, "\n".join(stale)


def test_tasks_resolve_without_importing_env_modules_by_hand():
    import subprocess
    import sys

    code = "from torchrl_tels.envs import get_task; print(get_task('pointmass-goal').env_id)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "torchrl_tels/PointMassGoal-v0"


def test_only_the_config_module_reads_a_hydra_config():
    # the recipe builds a typed RunSpec once (torchrl_tels.config); the library below never sees a DictConfig
    offenders = [f"{path.relative_to(PACKAGE.parent)} imports {name}"
                 for path in sorted(PACKAGE.rglob("*.py")) if path != PACKAGE / "config.py"
                 for name in imported_modules(path) if name.split(".")[0] in ("omegaconf", "hydra")]
    assert not offenders, "\n".join(offenders)
