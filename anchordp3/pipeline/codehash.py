"""What code made an output: a hash of the package modules a stage runs.

A stage's fingerprint covers the source of its entry module (``anchordp3.stages.render`` for
the render stage) and of every package module that one imports, directly or not, at the top or
inside a function (found by reading the import statements, not by importing), and of every module
of a package whose ``__init__`` imports them all by listing them (a registry of plug-ins: the tasks). Each module
counts by its syntax tree with docstrings left out, so editing a comment, a docstring or the
layout changes nothing, while any change to what the code does changes the hash and so marks
the stage's outputs as made by other code.

A task's own module (the one of ``sim/tasks/`` that declares its class) counts apart: ``code_hash``
leaves the task modules out when only the task registry brings them in, and ``task_hashes`` gives
each task the hash of its module, so changing one task's expert marks only that task's outputs as
made by other code (``schemas.manifest.Fingerprint.tasks``).

    code_hash(("anchordp3.stages.render",), exclude=task_modules().values())  # 64 hex digits
    task_hashes(("anchordp3.stages.render",), ["place_mouse"])  # {"place_mouse": 16 hex digits}
    stage_hashes(("anchordp3.stages.render",), ["place_mouse"])  # both, from one walk of the imports
"""

from __future__ import annotations

import ast
import hashlib
from collections.abc import Iterable
from functools import lru_cache
from pathlib import Path

import anchordp3

PACKAGE = "anchordp3"
TASKS_PACKAGE = "anchordp3.sim.tasks"  # the registry of task classes, one module per task or family
ROOT = Path(anchordp3.__file__).resolve().parent  # the package folder whose sources are hashed


def module_path(name: str, root: Path) -> Path | None:
    """The source file of package module ``name`` (``anchordp3.a.b``) under ``root``, or None."""
    parts = name.split(".")
    if parts[0] != PACKAGE:
        return None
    base = root.joinpath(*parts[1:])
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def imported_modules(name: str, tree: ast.Module, root: Path) -> set[str]:
    """Package modules that module ``name``'s source imports anywhere in it (absolute or relative)."""
    is_package = module_path(name, root) == root.joinpath(*name.split(".")[1:]) / "__init__.py"
    here = name.split(".") if is_package else name.split(".")[:-1]
    found: set[str] = set()
    for node in statements(tree):
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = here[: len(here) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            found.add(base)
            found.update(f"{base}.{a.name}" for a in node.names)  # `from pkg import module`
    if is_package and imports_every_module(tree):
        found.update(f"{name}.{p.stem}" for p in module_path(name, root).parent.iterdir()
                     if (p.suffix == ".py" and p.stem != "__init__") or (p / "__init__.py").is_file())
    return {m for m in found if m.split(".")[0] == PACKAGE and module_path(m, root) is not None}


def imports_every_module(tree: ast.Module) -> bool:
    """Whether a package's ``__init__`` imports all its modules by listing them
    (``pkgutil.iter_modules(__path__)``: a registry's plug-ins, the task classes of ``sim/tasks``),
    which no import statement names."""
    return any(isinstance(node, ast.Attribute) and node.attr == "iter_modules" for node in ast.walk(tree))


_BLOCKS = ("body", "orelse", "finalbody", "handlers", "cases")  # the fields of a node that hold statements


def statements(tree: ast.AST):
    """Every statement of ``tree`` (and the module itself, except handlers and match cases), at
    any depth: imports and docstrings are statements, so they are all here, without visiting the
    far more numerous expression nodes that ``ast.walk`` does."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        for field in _BLOCKS:
            children = getattr(node, field, None)
            if isinstance(children, list):
                todo.extend(children)


def with_parents(name: str) -> list[str]:
    """``a.b.c`` -> ``[a, a.b, a.b.c]``: importing a module runs its packages' ``__init__`` too."""
    parts = name.split(".")
    return [".".join(parts[: i + 1]) for i in range(len(parts))]


def module_closure(entries: Iterable[str], root: Path | None = None) -> list[str]:
    """Every package module that importing ``entries`` can run, sorted (root: the package folder,
    default ``ROOT``)."""
    return sorted(import_graph(entries, Path(root or ROOT)))


def import_graph(entries: Iterable[str], root: Path) -> dict[str, set[str]]:
    """Each package module that importing ``entries`` can run -> the package modules its source
    imports (``imported_modules``; importing one also runs its packages' ``__init__``)."""
    todo = [p for e in entries for p in with_parents(e)]
    graph: dict[str, set[str]] = {}
    while todo:
        name = todo.pop()
        if name in graph or module_path(name, root) is None:
            continue
        graph[name] = imported_modules(name, _parse(module_path(name, root)), root)
        todo.extend(p for m in graph[name] for p in with_parents(m))
    return graph


def code_hash(entries: Iterable[str], root: Path | None = None, exclude: Iterable[str] = ()) -> str:
    """sha256 (hex) over the docstring-free syntax trees of ``entries`` and all they import
    (root: the package folder, default ``ROOT``), but for the task modules in ``exclude`` that only
    the task registry imports (those ``task_hashes`` covers; a module another one imports stays)."""
    root = Path(root or ROOT)
    return _code_hash(import_graph(entries, root), set(exclude), root)


def task_hashes(entries: Iterable[str], tasks: Iterable[str], root: Path | None = None) -> dict[str, str]:
    """For each of ``tasks`` whose module the code of ``entries`` reaches: the first 16 hex digits of
    a sha256 over that module's syntax tree and those of the task modules it imports. Tasks the code
    does not reach (a stage that never builds a scene) are left out."""
    root = Path(root or ROOT)
    return _task_hashes(import_graph(entries, root), task_modules(root), tasks, root)


def stage_hashes(entries: Iterable[str], tasks: Iterable[str], root: Path | None = None) -> tuple[str, dict[str, str]]:
    """``code_hash`` of ``entries`` without the task modules and their ``task_hashes``, from one
    walk of the imports (what a data stage's fingerprint holds)."""
    root = Path(root or ROOT)
    graph, modules = import_graph(entries, root), task_modules(root)
    return _code_hash(graph, set(modules.values()), root), _task_hashes(graph, modules, tasks, root)


def _code_hash(graph: dict[str, set[str]], exclude: set[str], root: Path) -> str:
    """sha256 (hex) over the modules of ``graph`` but those of ``exclude`` that no module imports
    other than the task registry and ``exclude`` themselves."""
    kept = {m for name, imports in graph.items() if name != TASKS_PACKAGE and name not in exclude for m in imports}
    h = hashlib.sha256()
    for name in sorted(graph):
        if name not in exclude or name in kept:
            h.update(f"{name}\0{_digest(module_path(name, root))}\n".encode())
    return h.hexdigest()


def _task_hashes(graph: dict[str, set[str]], modules: dict[str, str], tasks: Iterable[str], root: Path) -> dict[str, str]:
    """``task_hashes`` from the import ``graph`` of a stage's code and ``modules`` (``task_modules``)."""
    family = set(modules.values())
    out: dict[str, str] = {}
    for task in tasks:
        module = modules.get(task)
        if module is None or module not in graph:
            continue
        h = hashlib.sha256()
        for name in _family_closure(module, family, graph):
            h.update(f"{name}\0{_digest(module_path(name, root))}\n".encode())
        out[task] = h.hexdigest()[:16]
    return out


def _family_closure(module: str, family: set[str], graph: dict[str, set[str]]) -> list[str]:
    """``module`` and the task modules of ``family`` it imports, directly or through one another
    (not through the registry, which imports them all), sorted."""
    todo, seen = [module], set()
    while todo:
        name = todo.pop()
        if name not in seen:
            seen.add(name)
            todo.extend(graph[name] & family)
    return sorted(seen)


def task_modules(root: Path | None = None) -> dict[str, str]:
    """Each task's name -> the module of ``sim/tasks/`` whose class declares its spec
    (``spec = PLACE_MOUSE``), read from the sources: the simulator is not imported. Empty when the
    package has no task registry."""
    root = Path(root or ROOT)
    init = module_path(TASKS_PACKAGE, root)
    if init is None or init.name != "__init__.py":
        return {}
    return {task: f"{TASKS_PACKAGE}.{path.stem}" for path in sorted(init.parent.glob("*.py")) if path.stem != "__init__"
            for task in _declared_tasks(str(path), *_stamp(path))}


@lru_cache(maxsize=256)
def _declared_tasks(path: str, mtime_ns: int, size: int) -> tuple[str, ...]:
    """The task names whose specs the classes of one version of ``path`` declare (``spec = NAME``)."""
    from anchordp3.schemas import tasks as specs

    names = [stmt.value.id for node in ast.walk(_parse(Path(path))) if isinstance(node, ast.ClassDef) for stmt in node.body
             if isinstance(stmt, ast.Assign) and isinstance(stmt.value, ast.Name)
             and any(isinstance(t, ast.Name) and t.id == "spec" for t in stmt.targets)]
    return tuple(spec.name for n in names if isinstance(spec := getattr(specs, n, None), specs.TaskSpec))


def _parse(path: Path) -> ast.Module:
    """``path``'s syntax tree with docstrings removed (imports intact), parsed once per version."""
    return _source(str(path), *_stamp(path))[0]


def _digest(path: Path) -> str:
    """sha256 of ``path``'s docstring-free syntax tree."""
    return _source(str(path), *_stamp(path))[1]


def _stamp(path: Path) -> tuple[int, int]:
    st = path.stat()
    return st.st_mtime_ns, st.st_size


@lru_cache(maxsize=1024)
def _source(path: str, mtime_ns: int, size: int) -> tuple[ast.Module, str]:
    tree = ast.parse(Path(path).read_bytes(), filename=path)
    for node in statements(tree):
        body = getattr(node, "body", None)
        if (isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and body
                and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant)
                and isinstance(body[0].value.value, str)):
            node.body = body[1:] or [ast.Pass()]
    return tree, hashlib.sha256(ast.dump(tree, include_attributes=False).encode()).hexdigest()
