"""The base of every policy's settings: the run's ``policy`` section and a policy's ``config.json``.

``policy.type`` picks the config class, as ``algo.name`` does the algorithm's: the registered
policy class of that saved ``type`` (``stepnft.policies.base.POLICY_TYPES``, plugins included)
names its :class:`PolicyConfig` subclass as ``config_class``, whose fields are then the
``--policy.*`` flags. The run reads the fields in :data:`RUN_FIELDS` of whichever config it
gets (the envs' chunking and the checks against the simulator), so every policy config declares
them; ``cameras`` is optional (none: a state policy).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, is_dataclass
from typing import ClassVar

from stepnft.settings import Settings

RUN_FIELDS = ("state_dim", "action_dim", "horizon", "n_exec")
"""What a run reads of every policy config: the state and action sizes the simulator must have,
the chunk length H and the actions executed per policy call."""


@dataclass
class PolicyConfig(Settings):
    """Settings of a policy type (subclass it with the policy's own fields, each with a type, a
    range and a docstring; ``stepnft.settings``); saved as the policy's ``config.json``."""

    type: ClassVar[str] = ""
    """The saved ``type`` of the policy this config builds (set by the subclass)."""
    section: ClassVar[str] = "policy"

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "PolicyConfig":
        """The config saved in a policy's ``config.json`` (without ``type``); an unknown key or a
        bad value is a ValueError naming it."""
        known = {f.name for f in fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown policy config keys {sorted(unknown)}; known: {sorted(known)}")
        return cls(**data)


def missing_run_fields(cls: type) -> list[str]:
    """The :data:`RUN_FIELDS` that config class ``cls`` does not declare."""
    declared = {f.name for f in fields(cls)} if is_dataclass(cls) else set()
    return [name for name in RUN_FIELDS if name not in declared]
