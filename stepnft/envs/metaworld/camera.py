"""Offscreen camera images of a MetaWorld scene: upright, shadows and reflections off.

MuJoCo renders on the CPU through Mesa (``MUJOCO_GL=egl``, or ``osmesa``). A frame costs about
20 ms whatever its size up to 128 px (the scene's meshes dominate), so the chunk env renders only
when the policy is called. Shadows and reflections are off (about 3x faster, and nothing a
policy needs). Several of MetaWorld's cameras (``corner``, ``corner2``, ...) are mounted upside
down; their images are turned by 180 degrees (a rotation, not a mirror), decided from each
camera's current orientation so a tilted camera (``camera_pose``) stays consistent.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from stepnft.envs.base import RenderingError
from stepnft.envs.rendering import quiet_teardown


class CameraRenderer:
    """Renders ``cameras`` of a MuJoCo model at ``height`` x ``width``."""

    def __init__(self, model, cameras: Sequence[str], height: int, width: int):
        # One llvmpipe thread per process: env workers render side by side, one per core, and
        # more threads per renderer did not render faster here. Read when Mesa loads.
        os.environ.setdefault("LP_NUM_THREADS", "1")
        os.environ.setdefault("MUJOCO_GL", "egl")
        import mujoco

        valid = [model.camera(i).name for i in range(model.ncam)]
        unknown = [c for c in cameras if c not in valid]
        if unknown:
            raise ValueError(f"unknown camera {unknown[0]!r}; this scene's cameras: {', '.join(valid)}")
        self.cameras = list(cameras)
        self._ids = [valid.index(c) for c in cameras]
        reason = None
        with quiet_teardown():
            try:
                self._renderer = mujoco.Renderer(model, height, width)
            except Exception as err:  # noqa: BLE001 - GL failures come as several error types
                reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        if reason is not None:  # raised here, once the half-built renderer was freed quietly
            raise RenderingError(f"offscreen rendering failed ({reason}): set MUJOCO_GL=egl "
                                 "and install libegl1 libegl-mesa0 (scripts/bootstrap.sh does)")
        flags = self._renderer.scene.flags
        flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0

    def frame(self, data, index: int = 0) -> np.ndarray:
        """Camera ``index``'s image, uint8 [height, width, 3], upright."""
        camera = self._ids[index]
        self._renderer.update_scene(data, camera=camera)
        image = self._renderer.render()
        # The camera's up axis (column 1 of its frame) pointing down: the image is upside down.
        if data.cam_xmat[camera][7] < 0:
            image = image[::-1, ::-1]
        return np.ascontiguousarray(image)

    def views(self, data) -> np.ndarray:
        """Every camera's image, uint8 [V, 3, height, width] (channels first, as convolutions take them)."""
        return np.stack([self.frame(data, v).transpose(2, 0, 1) for v in range(len(self._ids))])

    def close(self) -> None:
        self._renderer.close()
