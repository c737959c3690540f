"""Code fingerprints: a stage's hash follows the code it runs and nothing else."""

from __future__ import annotations

from pathlib import Path

from anchordp3.pipeline.codehash import ROOT, code_hash, module_closure, task_hashes, task_modules
from anchordp3.schemas.tasks import TASK_NAMES


def package(tmp_path: Path) -> Path:
    """A small package named like ours: ``a`` imports ``b`` inside a function, ``b`` imports
    ``sub.c`` relatively, ``d`` stands apart."""
    root = tmp_path / "anchordp3"
    (root / "sub").mkdir(parents=True)
    files = {
        "__init__.py": "",
        "a.py": '"""Module a."""\n\ndef f():\n    from anchordp3 import b\n    return b.g()\n',
        "b.py": "from .sub import c\n\ndef g():\n    return c.K + 1  # one more\n",
        "sub/__init__.py": "",
        "sub/c.py": "K = 1\n",
        "d.py": "import os\n",
    }
    for name, text in files.items():
        (root / name).write_text(text)
    return root


def test_the_closure_follows_imports_anywhere_in_a_module_and_stays_in_the_package(tmp_path) -> None:
    root = package(tmp_path)
    assert module_closure(["anchordp3.a"], root) == ["anchordp3", "anchordp3.a", "anchordp3.b", "anchordp3.sub", "anchordp3.sub.c"]
    assert module_closure(["anchordp3.d"], root) == ["anchordp3", "anchordp3.d"]


def test_a_package_that_imports_all_its_modules_by_listing_them_brings_them_all(tmp_path) -> None:
    root = package(tmp_path)
    (root / "plugins").mkdir()
    (root / "plugins" / "__init__.py").write_text(
        "import importlib\nimport pkgutil\n\nfor m in pkgutil.iter_modules(__path__):\n"
        "    importlib.import_module(f'{__name__}.{m.name}')\n")
    (root / "plugins" / "one.py").write_text("X = 1\n")
    (root / "e.py").write_text("from anchordp3 import plugins\n")
    assert module_closure(["anchordp3.e"], root) == ["anchordp3", "anchordp3.e", "anchordp3.plugins", "anchordp3.plugins.one"]
    before = code_hash(["anchordp3.e"], root)
    (root / "plugins" / "one.py").write_text("X = 2\n")
    assert code_hash(["anchordp3.e"], root) != before  # a plug-in's change is the stage's


def test_every_task_module_counts_in_the_render_stages_code() -> None:
    assert "anchordp3.sim.tasks.blocks" in module_closure(["anchordp3.stages.render"])


def test_the_hash_changes_with_the_code_a_stage_runs_and_nothing_else(tmp_path) -> None:
    root = package(tmp_path)
    before = code_hash(["anchordp3.a"], root)
    assert code_hash(["anchordp3.a"], root) == before
    (root / "b.py").write_text('"""Now documented."""\nfrom .sub import c\n\n\ndef g():\n    """g."""\n    return c.K + 1\n')
    (root / "d.py").write_text("import sys\n")
    assert code_hash(["anchordp3.a"], root) == before  # docstrings, comments, layout, unrelated modules
    (root / "sub" / "c.py").write_text("K = 2\n")
    assert code_hash(["anchordp3.a"], root) != before


def test_each_data_stage_hashes_its_own_modules() -> None:
    features = module_closure(["anchordp3.stages.features"])
    assert "anchordp3.geometry.features" in features and "anchordp3.stages.write" not in features
    assert "anchordp3.dataset.shard" in module_closure(["anchordp3.stages.write"])
    assert len(code_hash(["anchordp3.stages.features"], ROOT)) == 64


def test_fingerprints_say_what_changed_and_keep_outputs_adopts_only_code_changes() -> None:
    from anchordp3.pipeline.runner import adoptable, describe_changes
    from anchordp3.schemas.manifest import Fingerprint

    old = Fingerprint(code_version="0.1.0", code_hash="a", config_hash="c", upstream={"rollout": "x"})
    assert old.changes(old) == []
    assert old.changes(old.model_copy(update={"code_hash": "b"})) == ["code"]
    assert old.changes(old.model_copy(update={"config_hash": "d", "upstream": {"rollout": "y"}})) == ["config", "upstream rollout"]
    tasked = old.model_copy(update={"tasks": {"place_mouse": "m", "place_bell": "b"}})
    assert tasked.changes(tasked.model_copy(update={"tasks": {"place_mouse": "m", "place_bell": "c"}})) == ["task place_bell"]
    assert tasked.digest() == old.digest()  # downstream stages carry the tasks' hashes on themselves
    changes = {"rollout": ["code"], "anchors": ["upstream rollout"], "render": ["config", "upstream anchors"],
               "features": ["upstream render"]}
    assert adoptable(changes) == ["rollout", "anchors"]  # a config change is never kept, nor what follows it
    assert describe_changes({"features": ["code"], "write": ["upstream features"]}) == "features (code), write (upstream features)"


def with_tasks(root: Path) -> Path:
    """``package`` plus a task registry like ``sim/tasks``: one module declares place_mouse and
    place_bell, another place_phone_stand, a helper both import; stage ``s`` reaches them through
    the registry only."""
    tasks = root / "sim" / "tasks"
    tasks.mkdir(parents=True)
    (root / "sim" / "__init__.py").write_text("")
    (tasks / "__init__.py").write_text(
        "import importlib\nimport pkgutil\n\nfor m in pkgutil.iter_modules(__path__):\n"
        "    importlib.import_module(f'{__name__}.{m.name}')\n")
    (tasks / "helper.py").write_text("WIDTH = 1\n")
    (tasks / "scale.py").write_text("from anchordp3.sim.tasks.helper import WIDTH\n\n\nclass Mouse:\n    spec = PLACE_MOUSE\n\n\n"
                                    "class Bell:\n    spec = PLACE_BELL\n    size = WIDTH\n")
    (tasks / "phone.py").write_text("from anchordp3.sim.tasks import helper\n\n\nclass Phone:\n    spec = PLACE_PHONE_STAND\n")
    (root / "s.py").write_text("from anchordp3.sim import tasks\n")
    return root


def test_each_task_is_found_in_the_module_that_declares_its_spec(tmp_path) -> None:
    root = with_tasks(package(tmp_path))
    assert task_modules(root) == {"place_mouse": "anchordp3.sim.tasks.scale", "place_bell": "anchordp3.sim.tasks.scale",
                                  "place_phone_stand": "anchordp3.sim.tasks.phone"}
    assert task_modules(package(tmp_path / "other")) == {}  # no registry, no tasks
    assert set(task_modules()) == set(TASK_NAMES)  # the package's own: every registered task


def test_a_task_module_s_change_moves_that_task_s_hash_and_not_the_stage_s(tmp_path) -> None:
    root = with_tasks(package(tmp_path))
    tasks = ["place_mouse", "place_bell", "place_phone_stand"]
    apart = task_modules(root).values()
    code, before = code_hash(["anchordp3.s"], root, exclude=apart), task_hashes(["anchordp3.s"], tasks, root)
    assert before["place_mouse"] == before["place_bell"] != before["place_phone_stand"]  # one module, one hash
    assert task_hashes(["anchordp3.a"], tasks, root) == {}  # code that never reaches a task
    (root / "sim" / "tasks" / "phone.py").write_text("from anchordp3.sim.tasks import helper\n\n\nclass Phone:\n"
                                                     "    spec = PLACE_PHONE_STAND\n    lean = 2\n")
    after = task_hashes(["anchordp3.s"], tasks, root)
    assert code_hash(["anchordp3.s"], root, exclude=apart) == code
    assert after["place_phone_stand"] != before["place_phone_stand"] and after["place_mouse"] == before["place_mouse"]
    assert code_hash(["anchordp3.s"], root) != code_hash(["anchordp3.s"], root, exclude=apart)  # excluded they were
    (root / "sim" / "tasks" / "helper.py").write_text("WIDTH = 2\n")  # shared by all tasks: the stage's own code
    assert code_hash(["anchordp3.s"], root, exclude=apart) != code


def test_a_task_module_another_module_imports_stays_in_the_stage_s_code(tmp_path) -> None:
    root = with_tasks(package(tmp_path))
    (root / "t.py").write_text("from anchordp3.sim import tasks\nfrom anchordp3.sim.tasks import phone\n")
    apart = task_modules(root).values()
    before = code_hash(["anchordp3.t"], root, exclude=apart)
    (root / "sim" / "tasks" / "phone.py").write_text("class Phone:\n    spec = PLACE_PHONE_STAND\n    lean = 3\n")
    assert code_hash(["anchordp3.t"], root, exclude=apart) != before
