# SPDX-License-Identifier: Apache-2.0
"""The virtual fingertip's scene: a spec dict from a file, YAML text or dict, validated."""

from __future__ import annotations

import copy
import os

import yaml

from ae_tactile.sim.scene import SceneError, load_scene


def load_scene_spec(scene) -> dict:
    """A scene spec dict, validated once by loading it.

    Parameters
    ----------
    scene : str, os.PathLike or dict
        A scene file's path, YAML text (with a newline) or a spec dict (copied).

    Returns
    -------
    dict
        The spec; a file's spec gets its ``name`` from the file name if it has none.

    Raises
    ------
    ae_tactile.sim.scene.SceneError
        Anything that is not a valid scene (bad YAML, nesting too deep, unreadable file).
    """
    try:
        return _load_scene_spec(scene)
    except (RecursionError, yaml.YAMLError) as exc:
        raise SceneError(f"scene is not a valid scene file: {type(exc).__name__}") from None
    except OSError as exc:
        raise SceneError(f"scene cannot be read: {exc}") from None


def _load_scene_spec(scene) -> dict:
    if isinstance(scene, dict):
        spec = copy.deepcopy(scene)
    elif isinstance(scene, (str, os.PathLike)) and os.path.exists(str(scene)):
        with open(scene, encoding="utf-8") as fh:
            spec = yaml.safe_load(fh)
        if not isinstance(spec, dict):
            raise SceneError(f"scene file is not a YAML mapping: {scene}")
        spec.setdefault("name", os.path.splitext(os.path.basename(str(scene)))[0])
    else:
        spec = yaml.safe_load(scene) if isinstance(scene, str) and "\n" in scene else None
        if not isinstance(spec, dict):
            raise SceneError(f"scene file not found or not a YAML mapping: {scene!r}")
    load_scene(copy.deepcopy(spec))  # validate now: clear errors before anything runs
    return spec
