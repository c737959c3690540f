"""Pure-array geometry: depth back-projection, farthest point sampling, per-point features.

No sapien, ray or torch here; everything takes and returns numpy arrays in metres.
"""
