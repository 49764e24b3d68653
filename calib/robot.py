"""Where the Go2 description lives (the example-robot-data package ships no Python module)."""

from __future__ import annotations

import importlib.metadata
from functools import cache
from pathlib import Path


@cache
def go2_urdf_path() -> Path:
    """Absolute path of ``go2.urdf`` inside the installed example-robot-data package."""
    try:
        files = importlib.metadata.files("example-robot-data") or []
    except importlib.metadata.PackageNotFoundError as exc:  # pragma: no cover - install error
        raise RuntimeError("example-robot-data is not installed: pip install example-robot-data") from exc
    for f in files:
        if str(f).endswith("go2_description/urdf/go2.urdf"):
            return Path(f.locate()).resolve()
    raise RuntimeError("go2.urdf not found in the example-robot-data package")


def package_share_dir() -> Path:
    """``<site-packages>/cmeel.prefix/share``: the package_dirs pinocchio needs for meshes."""
    return go2_urdf_path().parents[4]


def go2_collision_mesh_dir() -> Path:
    """Folder of the Go2 collision meshes (MuJoCo cannot load the .dae visuals)."""
    return go2_urdf_path().parents[1] / "collisions"
