"""Render-only randomization: procedural textures, surface colours and lights.

Draws come from the episode's ``appearance`` stream, never from the physics streams.
"""

from __future__ import annotations

import numpy as np
import sapien

from anchordp3.schemas.randomization import RandomizationConfig


def procedural_texture(rng: np.random.Generator, size: int = 128) -> np.ndarray:
    """A random tileable texture, ``(size, size, 4)`` uint8 RGBA: one of value noise, stripes,
    checkers or wood grain, in two random colours."""
    c0, c1 = rng.uniform(0, 1, 3), rng.uniform(0, 1, 3)
    u, v = np.meshgrid(np.linspace(0, 1, size, endpoint=False), np.linspace(0, 1, size, endpoint=False))
    kind = rng.integers(4)
    if kind == 0:  # value noise, a few octaves of periodic bilinear noise
        t = np.zeros_like(u)
        for octave in range(4):
            n = 4 * 2**octave
            grid = rng.uniform(0, 1, (n, n))
            x, y = u * n, v * n
            x0, y0 = np.floor(x).astype(int) % n, np.floor(y).astype(int) % n
            fx, fy = x - np.floor(x), y - np.floor(y)
            a = grid[y0, x0] * (1 - fx) + grid[y0, (x0 + 1) % n] * fx
            b = grid[(y0 + 1) % n, x0] * (1 - fx) + grid[(y0 + 1) % n, (x0 + 1) % n] * fx
            t += (a * (1 - fy) + b * fy) / 2**octave
        t = (t - t.min()) / (np.ptp(t) + 1e-9)
    elif kind == 1:  # stripes at a random angle and frequency
        ang, freq = rng.uniform(0, np.pi), rng.integers(2, 12)
        t = 0.5 + 0.5 * np.sin(2 * np.pi * freq * (u * np.cos(ang) + v * np.sin(ang)))
    elif kind == 2:  # checkers
        n = rng.integers(2, 10)
        t = ((np.floor(u * n) + np.floor(v * n)) % 2).astype(np.float64)
    else:  # wood-like rings
        cx, cy, freq = rng.uniform(-1, 2), rng.uniform(-1, 2), rng.uniform(10, 40)
        t = 0.5 + 0.5 * np.sin(freq * np.hypot(u - cx, (v - cy) * 0.3) + 3 * np.sin(6 * np.pi * u))
    rgb = c0[None, None] * (1 - t[..., None]) + c1[None, None] * t[..., None]
    rgba = np.concatenate([rgb, np.ones_like(t)[..., None]], axis=-1)
    return (rgba * 255).astype(np.uint8)


def surface_material(rng: np.random.Generator, textured: bool, plain_prob: float, plain_rgba) -> sapien.render.RenderMaterial:
    """A render material: a procedural texture, or a plain colour (always when not ``textured``)."""
    if not textured:
        return sapien.render.RenderMaterial(base_color=list(plain_rgba))
    if rng.uniform() < plain_prob:
        return sapien.render.RenderMaterial(base_color=[*rng.uniform(0.2, 0.9, 3), 1.0])
    mat = sapien.render.RenderMaterial(base_color=[1.0, 1.0, 1.0, 1.0])
    mat.base_color_texture = sapien.render.RenderTexture2D(procedural_texture(rng), "R8G8B8A8Unorm", srgb=True)
    mat.roughness = float(rng.uniform(0.4, 1.0))
    return mat


class Lights:
    """Ambient, one directional and two point lights; randomised per episode when configured."""

    def __init__(self, scene: sapien.Scene, rng: np.random.Generator, cfg: RandomizationConfig):
        self.scene, self.rng, self.cfg = scene, rng, cfg
        self.crazy = bool(cfg.random_lights and rng.uniform() < cfg.crazy_light_prob)
        self.entities: list = []
        self._place(wild=self.crazy)

    def _place(self, wild: bool) -> None:
        for e in self.entities:
            self.scene.remove_light(e)
        self.entities = []
        r, cfg = self.rng, self.cfg
        if not cfg.random_lights:
            self.scene.set_ambient_light([0.5, 0.5, 0.5])
            self.entities.append(self.scene.add_directional_light([0.2, 0.6, -1.0], [0.6, 0.6, 0.6], shadow=False))
            for x in (-0.8, 0.8):
                self.entities.append(self.scene.add_point_light([x, 0.0, 2.0], [0.6, 0.6, 0.6], shadow=False))
            return
        top = 2.0 if wild else 1.0
        self.scene.set_ambient_light(list(r.uniform(0.15, 0.6 * top, 3)))
        d = np.array([r.uniform(-0.6, 0.6), r.uniform(-0.2, 0.8), -1.0])
        self.entities.append(self.scene.add_directional_light(list(d), list(r.uniform(0.3, 0.9 * top, 3)), shadow=False))
        for _ in range(2):
            pos = [r.uniform(-1.2, 1.2), r.uniform(-0.8, 0.8), r.uniform(1.2, 2.2)]
            self.entities.append(self.scene.add_point_light(pos, list(r.uniform(0.2, 1.0 * top, 3)), shadow=False))

    def before_render(self) -> None:
        """Called before every capture: in crazy-light mode the lights change every time."""
        if self.crazy:
            self._place(wild=True)
