"""Typed data contracts shared by every room: configs, records, layouts. Imports nothing of ours."""
