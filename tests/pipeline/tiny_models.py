"""Tiny training settings and data runs shared by the pipeline tests (real networks, a few steps)."""

from __future__ import annotations

DATA_STAGE_NAMES = ("rollout", "anchors", "render", "features", "write")


def tiny_data(name: str, tasks: list[str], seeds: str, **changes) -> dict:
    """A data run config at 64×48 pixels and 256 points, one 0.4-CPU worker per stage."""
    return {"name": name, "tasks": tasks, "seeds": seeds, "preset": "randomized",
            "cameras": {"width": 64, "height": 48}, "features": {"n_points": 256},
            "anchors": {"dagger": {"fraction": 0.2}}, "write": {"episodes_per_shard": 2, "validation_fraction": 0.25},
            "execution": {"pools": {s: {"workers": 1, "cpus": 0.4} for s in DATA_STAGE_NAMES}}, **changes}


def tiny_training(segmenter: int, classifier: int, policy: int, val_predict_samples: int = 2, **top) -> dict:
    """A training config of tiny networks trained for the given optimizer steps each."""
    return {
        "segmenter": {
            "model": {"set_abstraction": [{"npoint": 64, "radius": 0.05, "nsample": 8, "mlp": [16, 32]},
                                          {"npoint": 16, "radius": 0.15, "nsample": 8, "mlp": [32, 64]}],
                      "feature_propagation": [[32], [32]], "head_hidden": 32},
            "optim": {"steps": segmenter, "warmup_steps": min(5, segmenter // 3 or 1), "batch_size": 8},
        },
        "classifier": {"instructions": {"count": 240}, "optim": {"steps": classifier, "batch_size": 16, "warmup_steps": min(3, classifier // 3 or 1)}},
        "policy": {
            "model": {"unet": {"down_dims": [32, 64], "step_embed_dim": 32}, "point_encoder": {"hidden_dim": 32, "out_dim": 64}},
            "optim": {"steps": policy, "warmup_steps": min(5, policy // 3 or 1), "lr": 1e-3, "batch_size": 16},
            "val_predict_samples": val_predict_samples,
        },
        **top,
    }
