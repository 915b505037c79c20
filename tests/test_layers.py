"""No module of ldm_rl imports one on its own or a higher floor (the table in docs/conventions.md)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "ldm_rl"


def floors() -> dict[str, int]:
    """unit -> floor, read from the layer table of docs/conventions.md."""
    text = (ROOT / "docs" / "conventions.md").read_text()
    section = text[text.index("## Layers: who may import whom"):]
    table = {}
    for floor, modules in re.findall(r"^\| (\d+) \| ([^|]+) \|", section, flags=re.M):
        for name in re.findall(r"`([\w.]+)`", modules):
            table[name] = int(floor)
    return table


def unit_of(dotted: str, table: dict[str, int]) -> str | None:
    """``ldm_rl.planning.q_map.x`` -> ``planning.q_map``; the longest table entry that prefixes the name."""
    parts = dotted.split(".")[1:]
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in table:
            return ".".join(parts[:n])
    return None


def imports(path: Path) -> list[tuple[int, str]]:
    """(line, dotted name) of every ldm_rl import in ``path``, at any depth (lazy imports included)."""
    found = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.split(".")[0] == "ldm_rl":
            found += [(node.lineno, f"{node.module}.{alias.name}") for alias in node.names]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names if alias.name.split(".")[0] == "ldm_rl"]
    return found


def test_the_layer_table_covers_every_module():
    table = floors()
    assert len(table) >= 20
    faces = {PACKAGE / "__init__.py", PACKAGE / "planning" / "__init__.py"}  # re-export from below
    uncovered = [str(p.relative_to(ROOT)) for p in PACKAGE.rglob("*.py") if p not in faces
                 and unit_of("ldm_rl." + ".".join(p.relative_to(PACKAGE).with_suffix("").parts), table) is None]
    assert not uncovered, f"modules on no floor of docs/conventions.md: {uncovered}"


def test_no_import_runs_up_or_sideways():
    table = floors()
    bad = []
    for path in PACKAGE.rglob("*.py"):
        module = "ldm_rl." + ".".join(path.relative_to(PACKAGE).with_suffix("").parts)
        own = unit_of(module, table)
        if own is None:  # a package face (ldm_rl/__init__.py, planning/__init__.py): it re-exports from below
            continue
        for line, name in imports(path):
            target = unit_of(name, table)
            if target is None or target == own:
                continue
            if table[target] >= table[own]:
                bad.append(f"{path.relative_to(ROOT)}:{line} ({own}, floor {table[own]}) imports {name} "
                           f"({target}, floor {table[target]})")
    assert not bad, "imports that run up or sideways:\n" + "\n".join(bad)


def test_the_check_catches_an_upward_import(tmp_path):
    """The checker itself: a model importing an agent is on floor 3 importing floor 8."""
    table = floors()
    fake = tmp_path / "q_fcn.py"
    fake.write_text("def f():\n    from ldm_rl.agents.base import Agent\n")
    (line, name), = imports(fake)
    assert unit_of(name, table) == "agents" and table["agents"] > table[unit_of("ldm_rl.models.q_fcn", table)]
