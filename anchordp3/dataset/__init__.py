"""The sharded training dataset: write one shard, read samples back, verify, torch loading.

Imports ``anchordp3.schemas`` and storage/array libraries only (nothing of sim, stages, pipeline).
"""
