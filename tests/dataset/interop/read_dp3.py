"""Read a DP3 export the way DP3 does, with zarr 2 (run by the interop venv's python).

    python read_dp3.py OUT.zarr  ->  prints one JSON line describing what was read

Follows ``ReplayBuffer.copy_from_path`` of 3D-Diffusion-Policy: ``zarr.open(path, 'r')``, every
``meta`` array, ``data[key][:]`` for state, action and point_cloud, then the checks its
constructor makes (each data array as long as the last episode end), and cuts episodes
``[ends[i-1], ends[i])`` as its ``get_episode`` does.
"""

import hashlib
import json
import sys

import numpy as np
import zarr


def main(path: str) -> None:
    root = zarr.open(path, "r")
    meta = {k: (np.array(v) if len(v.shape) == 0 else v[:]) for k, v in root["meta"].items()}
    data = {k: root["data"][k][:] for k in ("state", "action", "point_cloud")}
    ends = meta["episode_ends"]
    assert all(v.shape[0] == ends[-1] for v in data.values()), "a data array is not as long as the episodes"
    starts = np.concatenate([[0], ends[:-1]])
    lengths = [int(b - a) for a, b in zip(starts, ends)]
    first = {k: v[starts[0]:ends[0]] for k, v in data.items()}
    print(json.dumps({
        "zarr_version": zarr.__version__,
        "zgroup": ".zgroup" in root.store,
        "shapes": {k: list(v.shape) for k, v in data.items()},
        "dtypes": {k: str(v.dtype) for k, v in data.items()},
        "episode_ends": ends.tolist(), "lengths": lengths,
        "first_episode_frames": len(first["state"]),
        "sha256": {k: hashlib.sha256(np.ascontiguousarray(v).tobytes()).hexdigest() for k, v in data.items()},
        "meta_keys": sorted(meta),
    }))


if __name__ == "__main__":
    main(sys.argv[1])
