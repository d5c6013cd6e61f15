"""Perturbations (``stepnft.envs.perturbations``) applied to a MetaWorld v3 scene.

Each reset first restores the nominal model, then edits it for the episode, so nothing carries
over between episodes:

- ``table_color`` / ``floor_color`` / ``object_color``: ``geom_rgba`` of the visible geoms of
  the table, the floor, or the task's objects (a geom colour overrides its material's colour and
  tints its texture);
- ``lighting``: diffuse and specular light of every light and of the headlight, times a factor;
- ``camera_pose``: every camera shifted (``cam_pos``) and tilted (``cam_quat``);
- ``friction``: sliding friction of every geom, times a factor;
- ``mass``: mass and inertia of the task's object bodies, times a factor;
- ``object_position``: the task's random vector of initial object and goal positions is drawn
  from its range grown horizontally (``POSITION_MARGIN``), outside the range itself (each
  object or goal whose horizontal position varies lands outside its own range); the state then
  reports the goal unclipped;
- ``action_noise`` acts in the chunk env's ``step`` (Gaussian noise on every action).

The task's objects are the bodies below the world that are not the table, the wall, the robot
or its mocap target.
"""

from __future__ import annotations

import numpy as np
from gymnasium.spaces import Box

SCENE_BODIES = ("tablelink", "RetainingWall", "base", "mocap")
"""Top-level bodies of every MetaWorld scene that are not the task's objects."""

MODEL_FIELDS = ("geom_rgba", "light_diffuse", "light_specular", "cam_pos", "cam_quat", "geom_friction",
                "body_mass", "body_inertia")
"""The model arrays perturbations edit (restored at every reset)."""

VISIBLE_GROUPS = 2
"""Geom groups 0..2 are drawn by default; MetaWorld's collision meshes sit in group 3 and up."""


class ModelPerturber:
    """Edits one MetaWorld env's MuJoCo model for an episode and restores it."""

    def __init__(self, sim):
        model = self.model = sim.model
        self.sim = sim
        root = np.arange(model.nbody)
        for b in range(model.nbody):  # bodies are stored parents first
            root[b] = b if model.body_parentid[b] == 0 else root[model.body_parentid[b]]
        scene = {model.body(name).id for name in SCENE_BODIES}
        self.object_bodies = np.array([b for b in range(1, model.nbody) if root[b] not in scene], dtype=np.int64)
        visible = (model.geom_group <= VISIBLE_GROUPS) & (model.geom_rgba[:, 3] > 0)
        geom_root = root[model.geom_bodyid]
        self.geoms = {
            "table_color": np.flatnonzero(visible & (geom_root == model.body("tablelink").id)),
            "floor_color": np.flatnonzero(visible & (model.geom_bodyid == 0)),
            "object_color": np.flatnonzero(visible & np.isin(model.geom_bodyid, self.object_bodies)),
        }
        self._nominal = {name: getattr(model, name).copy() for name in MODEL_FIELDS}
        light = model.vis.headlight
        self._headlight = (light.diffuse.copy(), light.specular.copy())

    def restore(self) -> None:
        for name, value in self._nominal.items():
            getattr(self.model, name)[:] = value
        self.model.vis.headlight.diffuse[:], self.model.vis.headlight.specular[:] = self._headlight
        self.sim.__dict__.pop("_get_state_rand_vec", None)
        self.sim.__dict__.pop("sawyer_observation_space", None)

    def apply(self, params: dict[str, dict]) -> None:
        """Restore the nominal model, then apply one episode's ``params`` (before the sim's reset)."""
        self.restore()
        m = self.model
        for name, p in params.items():
            if name in self.geoms:
                m.geom_rgba[self.geoms[name], :3] = p["rgb"]
            elif name == "lighting":
                for array in (m.light_diffuse, m.light_specular, m.vis.headlight.diffuse, m.vis.headlight.specular):
                    array[:] = np.clip(array * p["factor"], 0.0, 1.0)
            elif name == "camera_pose":
                m.cam_pos[:] += p["shift"]
                half = np.radians(p["degrees"]) / 2
                turn = np.concatenate([[np.cos(half)], np.sin(half) * p["axis"]])
                m.cam_quat[:] = [_quat_mul(q, turn) for q in m.cam_quat]
            elif name == "friction":
                m.geom_friction[:, 0] *= p["factor"]
            elif name == "mass":
                m.body_mass[self.object_bodies] *= p["factor"]
                m.body_inertia[self.object_bodies] *= p["factor"]
            elif name == "object_position":
                self._positions_outside_range(p["margin"])

    def _positions_outside_range(self, margin: float) -> None:
        sim = self.sim
        low, high = sim._random_reset_space.low, sim._random_reset_space.high
        width = high - low
        horizontal = np.arange(len(low)) % 3 < 2
        grow = np.where(horizontal, margin * width, 0.0)
        blocks = [slice(i, i + 3) for i in range(0, len(low), 3) if (grow[i:i + 3] > 0).any()]

        def outside_range() -> np.ndarray:
            # Drawn from the env's generator like MetaWorld's own vector; each varying block
            # (an object's or the goal's xyz) lies outside its training range.
            while True:
                vec = sim.np_random.uniform(low - grow, high + grow)
                if all(((vec[b] < low[b]) | (vec[b] > high[b])).any() for b in blocks):
                    sim._last_rand_vec = vec
                    return vec

        sim._get_state_rand_vec = outside_range
        # MetaWorld clips the observed goal to its training range: report it as it is.
        space = sim.sawyer_observation_space
        goal = slice(len(space.low) - 3, None)
        low_obs, high_obs = space.low.copy(), space.high.copy()
        low_obs[goal], high_obs[goal] = -np.inf, np.inf
        sim.sawyer_observation_space = Box(low_obs, high_obs, dtype=np.float64)


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of quaternions (w, x, y, z), normalised."""
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    q = np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                  w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])
    return q / np.linalg.norm(q)
