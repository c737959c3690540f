"""anchordp3: AnchorDP3 as a multi-stage data pipeline.

Rooms (dependencies point down this list): ``schemas`` → ``geometry`` → ``sim`` → ``models`` →
``stages`` → ``pipeline`` → ``cli``. Only ``sim`` imports sapien; only ``pipeline`` imports ray.
"""

__version__ = "0.1.0"
