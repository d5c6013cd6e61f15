"""The rollout batch: every key the collector writes and the algorithms read, declared once.

Three tables linked by indices, built once by the collector and never patched:

=========  =====  ==============================================================================
table      rows   keys
=========  =====  ==============================================================================
episodes   E      ``episode_success`` bool, ``episode_task`` int64, ``episode_length`` int64 (env
                  steps), ``episode_seed`` int64 (the reset seed, -1 if the reset was unseeded)
calls      C      one row per policy call: ``obs`` (dict: ``state`` float32 [C, S], ``task``
                  int64 [C], with cameras ``image`` uint8 [C, V, 3, H, W], with semantic
                  perturbations ``instruction`` int64 [C]), ``actions`` float32 [C, H, A] (the sampled chunk),
                  ``mask`` bool [C, H] (positions executed), ``reward`` float32 [C] (summed over
                  the executed steps), ``done`` bool [C] (the episode ended in this call),
                  ``episode`` int64 [C] (its row in the episode table)
steps      N      one row per recorded denoising step: ``call`` int64 [N] (its row in the call
                  table), ``x_t``, ``x_next``, ``v_old`` float32 [N, H, A], ``t``, ``dt`` float32 [N]
=========  =====  ==============================================================================

Observations are stored once per policy call, however many of its denoising steps are
recorded. Labels, advantages and weights are the algorithm's business: it derives them from the
episode table (``step_success``, ``step_episode``).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

EPISODE_KEYS = ("episode_success", "episode_task", "episode_length", "episode_seed")
CALL_KEYS = ("actions", "mask", "reward", "done", "episode")
STEP_KEYS = ("call", "x_t", "x_next", "v_old", "t", "dt")
OBS_KEYS = ("state", "task")
"""Observation keys every simulator provides (camera simulators add ``image``)."""

_DTYPES = {
    "episode_success": torch.bool, "episode_task": torch.int64, "episode_length": torch.int64,
    "episode_seed": torch.int64, "mask": torch.bool, "done": torch.bool, "episode": torch.int64,
    "call": torch.int64, "task": torch.int64, "instruction": torch.int64, "image": torch.uint8,
}


@dataclass
class Batch:
    """Episodes, policy calls and recorded denoising steps of one iteration (see module doc)."""

    episode_success: Tensor
    episode_task: Tensor
    episode_length: Tensor
    episode_seed: Tensor
    obs: dict[str, Tensor]
    actions: Tensor
    mask: Tensor
    reward: Tensor
    done: Tensor
    episode: Tensor
    call: Tensor
    x_t: Tensor
    x_next: Tensor
    v_old: Tensor
    t: Tensor
    dt: Tensor

    def __post_init__(self) -> None:
        self.validate()

    # --- sizes ------------------------------------------------------------------------
    @property
    def num_episodes(self) -> int:
        return int(self.episode_success.shape[0])

    @property
    def num_calls(self) -> int:
        return int(self.episode.shape[0])

    @property
    def num_steps(self) -> int:
        return int(self.call.shape[0])

    @property
    def env_steps(self) -> int:
        return int(self.episode_length.sum())

    # --- derived views ------------------------------------------------------------------
    @property
    def step_episode(self) -> Tensor:
        """``[N]`` episode row of every recorded step."""
        return self.episode[self.call]

    @property
    def step_success(self) -> Tensor:
        """``[N]`` bool: whether the step's episode succeeded."""
        return self.episode_success[self.step_episode]

    @property
    def step_task(self) -> Tensor:
        """``[N]`` task index of every recorded step."""
        return self.obs["task"][self.call]

    def steps_obs(self, idx: Tensor) -> dict[str, Tensor]:
        """The observations of recorded steps ``idx`` (gathered from their calls)."""
        return self.calls_obs(self.call[idx])

    def calls_obs(self, calls: Tensor) -> dict[str, Tensor]:
        """The observations of policy calls ``calls``."""
        return {k: v[calls] for k, v in self.obs.items()}

    # --- building -------------------------------------------------------------------------
    def validate(self) -> None:
        """Check every declared key is present with the right leading size and dtype."""
        sizes = {"episodes": self.episode_success.shape[0], "calls": self.episode.shape[0], "steps": self.call.shape[0]}
        tables = [("episodes", EPISODE_KEYS), ("calls", CALL_KEYS), ("steps", STEP_KEYS)]
        for table, keys in tables:
            for key in keys:
                self._check(key, getattr(self, key), sizes[table], table)
        missing = [k for k in OBS_KEYS if k not in self.obs]
        if missing:
            raise ValueError(f"batch obs lacks {missing}")
        for key, value in self.obs.items():
            self._check(key, value, sizes["calls"], "calls")

    @staticmethod
    def _check(key: str, value: Tensor, rows: int, table: str) -> None:
        if not torch.is_tensor(value) or value.shape[0] != rows:
            shape = tuple(value.shape) if torch.is_tensor(value) else type(value).__name__
            raise ValueError(f"batch key {key!r} must have {rows} rows (the {table} table), got {shape}")
        want = _DTYPES.get(key, torch.float32)
        if key != "state" and value.dtype != want:
            raise ValueError(f"batch key {key!r} must be {want}, got {value.dtype}")

    @classmethod
    def concat(cls, batches: list["Batch"]) -> "Batch":
        """Stack batches (e.g. the parts of a plan played by several workers) into one, re-pointing the ``episode`` and ``call`` links."""
        episode_offset = call_offset = 0
        parts: dict[str, list[Tensor]] = {f.name: [] for f in fields(cls) if f.name != "obs"}
        obs: dict[str, list[Tensor]] = {k: [] for k in batches[0].obs}
        for b in batches:
            for name in parts:
                value = getattr(b, name)
                if name == "episode":
                    value = value + episode_offset
                elif name == "call":
                    value = value + call_offset
                parts[name].append(value)
            for k in obs:
                obs[k].append(b.obs[k])
            episode_offset += b.num_episodes
            call_offset += b.num_calls
        return cls(obs={k: torch.cat(v) for k, v in obs.items()}, **{k: torch.cat(v) for k, v in parts.items()})
