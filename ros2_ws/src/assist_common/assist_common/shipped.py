"""Where the shipped model files are: one lookup for every package (no rclpy import).

The repository keeps the trained weights and their cards in `models/` at its root. The packages'
setup.py files install them into `share/<package>/models/` (plain `colcon build`,
`--symlink-install` and pip alike), so an installed workspace finds them through the ament index
while a source checkout or editable install falls back to the repository's `models/`.
`$ASSIST_MODELS_DIR` overrides both.
"""
from __future__ import annotations

import os
from pathlib import Path

MODELS_ENV = 'ASSIST_MODELS_DIR'


def _share_dir(package: str) -> Path | None:
    """share/<package>/models of the package in the ament index, or None when it is not indexed."""
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory(package)) / 'models'
    except (ImportError, LookupError, OSError, ValueError):
        return None  # no AMENT_PREFIX_PATH (editable install) or the package is not in it


def _checkout_dir(filename: str) -> Path | None:
    """models/ of the source checkout this module lies in (resolving symlinks), if it holds `filename`."""
    for parent in Path(__file__).resolve().parents:
        cand = parent / 'models'
        if (cand / filename).is_file():
            return cand
    return None


def shipped_model_path(package: str, filename: str) -> Path:
    """Path of a shipped model file of `package`: $ASSIST_MODELS_DIR, else share/<package>/models, else <repo>/models.

    The returned path may not exist (the first candidate is returned then), so a caller's error
    message names where the file was expected.
    """
    env = os.environ.get(MODELS_ENV)
    if env:
        return Path(env).expanduser() / filename
    share = _share_dir(package)
    if share is not None and (share / filename).is_file():
        return share / filename
    checkout = _checkout_dir(filename)
    if checkout is not None:
        return checkout / filename
    if share is not None:
        return share / filename
    return Path(__file__).resolve().parents[4] / 'models' / filename
