"""Fixtures shared by the pipeline tests: one small Ray for the whole session."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def ray_session():
    """A local Ray with 2 logical CPUs and a small object store, started once per test session
    (``runner.ensure_ray`` then finds it and joins it); shut down at the end."""
    import ray

    from anchordp3.pipeline.runner import keep_ray_on_loopback

    started = not ray.is_initialized()
    if started:
        keep_ray_on_loopback()
        ray.init(num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1", object_store_memory=80 * 1024**2,
                 logging_level="WARNING", log_to_driver=False)
    yield ray
    if started:
        ray.shutdown()
