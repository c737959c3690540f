"""Config sections given in part: the fields left out keep their section's own default.

A field such as ``SegmenterTrainingConfig.optim`` has a default of its own (learning rate 1e-3, a
50-step warm-up) that differs from ``OptimizerConfig``'s bare defaults (1e-4, 500). Plain pydantic
validates ``segmenter: {optim: {steps: 3000}}`` into ``OptimizerConfig(steps=3000)``, silently
trading the section's defaults for the class's; ``PartialSections`` overlays what is given on the
field's default instead, at every depth, so a YAML file means the same read by any loader. A
section that names a ``preset`` (``PolicyConfig``) starts from that preset instead.
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, model_validator


def overlay(base: dict, given: dict) -> dict:
    """``given`` laid over ``base``, mappings merged key by key at every depth, anything else replaced
    (a mapping that names a ``preset`` too: it starts from that preset, not from ``base``)."""
    out = dict(base)
    for key, value in given.items():
        merge = isinstance(value, dict) and value.get("preset") is None and isinstance(out.get(key), dict)
        out[key] = overlay(out[key], value) if merge else value
    return out


class PartialSections(BaseModel):
    """Base of configs whose nested sections may be given in part (module docstring)."""

    @model_validator(mode="before")
    @classmethod
    def _overlay_section_defaults(cls, data: Any) -> Any:
        if not isinstance(data, dict):
            return data
        out = dict(data)
        for name, field in cls.model_fields.items():
            given = out.get(name)
            if isinstance(given, dict) and given.get("preset") is None and field.default_factory is not None:
                default = field.default_factory()
                if isinstance(default, BaseModel):
                    out[name] = overlay(default.model_dump(mode="json"), given)
        return out
