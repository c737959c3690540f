"""Orchestration: running stages over items, progress, runs. The only room that knows about Ray."""
