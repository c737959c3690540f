"""The rooms of the package and which way their imports go, read from the sources (nothing imported).

A room is a top-level folder (or module) of ``anchordp3``. Imports go one way, so there is no cycle:
schemas below everything; the simulator, geometry, models and datasets on the schemas; stages on
those; the pipeline (the only room that knows Ray) on the stages; the command line on top. SAPIEN
is used in ``sim/`` only.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "anchordp3"
MAY_IMPORT = {  # room: the rooms it may import
    "schemas": set(),
    "logs": set(),
    "viz": set(),
    "geometry": set(),
    "sim": {"schemas"},
    "models": {"schemas"},
    "dataset": {"schemas"},
    "stages": {"schemas", "sim", "geometry", "models", "dataset", "viz"},
    "pipeline": {"schemas", "sim", "geometry", "models", "dataset", "viz", "stages", "logs"},
    "cli": {"schemas", "sim", "stages", "pipeline", "viz", "logs"},
}
ONLY_IN = {"sapien": {"sim"}, "ray": {"pipeline"}}  # third-party packages and the rooms that may use them


def room_of(path: Path) -> str:
    rel = path.relative_to(PACKAGE)
    return rel.parts[0].removesuffix(".py")


def imports(path: Path) -> set[str]:
    """Every module ``path`` imports, anywhere in it (top level or inside a function)."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
    return found


SOURCES = sorted(p for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" or p.parent != PACKAGE)


def test_every_room_is_declared():
    assert {room_of(p) for p in SOURCES} <= set(MAY_IMPORT), sorted({room_of(p) for p in SOURCES} - set(MAY_IMPORT))


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_go_one_way(path):
    room = room_of(path)
    wrong = []
    for module in imports(path):
        top, *rest = module.split(".")
        if top == "anchordp3" and rest and rest[0] != room and rest[0] not in MAY_IMPORT[room] and rest[0] != "__init__":
            wrong.append(module)
        if top in ONLY_IN and room not in ONLY_IN[top]:
            wrong.append(module)
    assert not wrong, f"{room}/ may not import {sorted(wrong)}"


def test_the_declared_rooms_have_no_cycle():
    seen, order = set(), []

    def visit(room: str, stack: tuple[str, ...]) -> None:
        assert room not in stack, f"cycle: {' -> '.join(stack + (room,))}"
        if room in seen:
            return
        for dep in sorted(MAY_IMPORT[room]):
            visit(dep, stack + (room,))
        seen.add(room)
        order.append(room)

    for room in MAY_IMPORT:
        visit(room, ())
    assert order[0] in {"schemas", "logs", "viz", "geometry"}
