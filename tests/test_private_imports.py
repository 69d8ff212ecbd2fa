"""No module of the product or its benches imports another module's private (`_name`) helper: what other
modules use is public, so that a module's underscore names can change without breaking anything else."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("api", "workers", "shared", "services", "cli", "client", "bench")


def private_imports(path: Path) -> list[str]:
    """`from M import _name` statements of a file, as 'file:line M._name'."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.ImportFrom):
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    out.append(f"{path.relative_to(ROOT)}:{node.lineno} {node.module}.{alias.name}")
    return out


def test_no_private_name_is_imported_across_modules():
    found = [
        hit for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py")) for hit in private_imports(p)
    ]
    assert found == [], "\n".join(found)


def test_the_check_finds_a_private_import(tmp_path, monkeypatch):
    monkeypatch.setattr("test_private_imports.ROOT", tmp_path)
    (tmp_path / "m.py").write_text("from a.b import _hidden, public\nfrom c import __version__\n")
    assert private_imports(tmp_path / "m.py") == ["m.py:1 a.b._hidden"]
