"""The packages form one-way layers: each imports only the layers below it.

d2a_envs (envs, sensors) <- collectors (data, evaluation) <- d2a_agents (world model, policies)
<- benchmarks <- d2a (the CLI and the demo). Read from the source with ``ast``: an import
inside a function counts as much as one at the top.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYERS = ["d2a_envs", "collectors", "d2a_agents", "benchmarks", "d2a"]


def imported_packages(path: Path) -> set[str]:
    """Top-level package names that a source file imports (absolute imports only)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("layer", LAYERS)
def test_a_layer_imports_nothing_above_it(layer):
    above = set(LAYERS[LAYERS.index(layer) + 1 :])
    offenders = {
        str(path.relative_to(ROOT)): sorted(imported_packages(path) & above)
        for path in sorted((ROOT / layer).rglob("*.py"))
        if imported_packages(path) & above
    }
    assert not offenders, f"{layer} imports from a layer above it: {offenders}"


def test_the_check_sees_imports_inside_functions(tmp_path):
    source = tmp_path / "module.py"
    source.write_text("def f():\n    from d2a_agents.policy import agent\n    import benchmarks.success\n")
    assert imported_packages(source) == {"d2a_agents", "benchmarks"}
