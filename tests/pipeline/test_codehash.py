"""Code fingerprints: a stage's hash follows the code it runs and nothing else."""

from __future__ import annotations

from pathlib import Path

from anchordp3.pipeline.codehash import ROOT, code_hash, module_closure


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
    changes = {"rollout": ["code"], "anchors": ["upstream rollout"], "render": ["config", "upstream anchors"],
               "features": ["upstream render"]}
    assert adoptable(changes) == ["rollout", "anchors"]  # a config change is never kept, nor what follows it
    assert describe_changes({"features": ["code"], "write": ["upstream features"]}) == "features (code), write (upstream features)"
