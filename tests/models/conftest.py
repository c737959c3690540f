"""Model-room test settings: no hub access (the one-thread fixture is in ``tests/conftest.py``)."""

from __future__ import annotations

import os

os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
