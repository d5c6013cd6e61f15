"""The record of one demonstration, as simulators produce it: their scripted experts (through
``stepnft.data.demos.generate_demos``) and their own dataset readers (``Simulator.load_dataset``,
e.g. LIBERO's HDF5 files). It lives in the envs layer so that simulators can build it without
importing ``stepnft.data``, which stores and chunks it (``stepnft.data.demos.DemoEpisode`` is
this class)."""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass
class DemoEpisode:
    """One demonstration; T is its number of actions."""

    task: str
    instruction: str
    observations: np.ndarray
    """float32 [T+1, S]"""
    actions: np.ndarray
    """float32 [T, A]"""
    rewards: np.ndarray
    """float32 [T]"""
    successes: np.ndarray
    """bool [T]"""
    success: bool
    seed: int
    images: np.ndarray | None = None
    """uint8 [T+1, V, 3, H, W] camera views, when generated with cameras"""
