"""The SAPIEN world: scene, robot, cameras, randomization, objects, expert, tasks.

The only room that imports ``sapien``.
"""
