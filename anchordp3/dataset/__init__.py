"""The sharded training dataset: write one shard, read samples back, verify, torch loading, and
exports to other projects' formats (LeRobot v3.0, DP3 zarr).

Imports ``anchordp3.schemas`` and storage/array libraries only (nothing of sim, stages, pipeline).
"""
