"""Perturbations of the simulated world: out-of-distribution suites and training randomisation.

Import-light (no simulator): the config checks names here, and the simulators apply the
parameters drawn here to their own models (``stepnft.envs.metaworld.perturb``).

Suites (``stepnft eval --suite NAME``) group perturbations by what they shift:

=========  ========================================================================================
suite      perturbations
=========  ========================================================================================
ind        none: the training distribution (with the run's own ``env.randomize``, if any)
vision     ``table_color``, ``floor_color``, ``object_color`` (hues never used in training),
           ``lighting`` (intensity), ``camera_pose`` (shift and tilt of the cameras)
semantic   ``paraphrase`` (held-out rewordings of each task's instruction), ``distractor`` (the
           instruction inside unrelated words)
execution  ``object_position`` (initial object and goal positions outside the task's range),
           ``action_noise``, ``friction``, ``mass`` (of the task's objects)
=========  ========================================================================================

Every perturbation has a *training* range and a disjoint *held-out* range (``RANGES``,
``HUE_BINS``, the paraphrase and distractor lists), so a policy trained with
``env.randomize`` never sees a held-out value. ``Perturbations(names, heldout=False)`` is
training randomisation: every named perturbation applies to every episode. With
``heldout=True`` (the suites) each episode gets one of them: the one at ``seed % len(names)``
for a seeded reset, so the episodes of an evaluation cycle through them in equal shares.

Episode parameters depend only on the reset seed (``episode_rng``), never on what ran before.
"""

from __future__ import annotations

import colorsys
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from stepnft.names import split_names

SUITES: dict[str, tuple[str, ...]] = {
    "ind": (),
    "vision": ("table_color", "floor_color", "object_color", "lighting", "camera_pose"),
    "semantic": ("paraphrase", "distractor"),
    "execution": ("object_position", "action_noise", "friction", "mass"),
}
"""Evaluation suites and their perturbations (see the module doc)."""

OOD_SUITES = ("vision", "semantic", "execution")
"""The suites averaged into the OOD average."""

FAMILY: dict[str, str] = {name: suite for suite, names in SUITES.items() for name in names}
"""The suite each perturbation belongs to."""

RANGES: dict[str, tuple[tuple[tuple[float, float], ...], tuple[tuple[float, float], ...]]] = {
    "lighting": (((0.8, 1.25),), ((0.35, 0.6), (1.6, 2.5))),
    "camera_shift": (((0.0, 0.01),), ((0.02, 0.04),)),
    "camera_tilt": (((0.0, 1.0),), ((2.0, 4.0),)),
    "action_noise": (((0.0, 0.05),), ((0.1, 0.2),)),
    "friction": (((0.8, 1.25),), ((0.4, 0.6), (1.7, 2.5))),
    "mass": (((0.8, 1.25),), ((0.3, 0.5), (2.0, 3.0))),
}
"""(training intervals, held-out intervals) of each scalar: light intensity factor, camera shift
(m) and tilt (degrees), std of the Gaussian noise added to each action, factors on the sliding
friction of every geom and on the mass of the task's objects. A value is drawn from one
interval picked at random (scale factors log-uniformly)."""

LOG_UNIFORM = {"lighting", "friction", "mass"}

HUE_BINS = 12
"""Colour hues are split into this many bins: even bins are training hues, odd bins held out."""

POSITION_MARGIN = 0.5
"""``object_position`` draws horizontal positions from the task's range grown by this fraction
of its width on each side, outside the range itself."""

TRAIN_DISTRACTORS = ("{} please", "now {}", "robot, {}", "{} carefully")
"""Distractor templates used in training randomisation (``{}`` is the instruction)."""

HELDOUT_DISTRACTORS = (
    "there is a blue cup on the shelf; {}",
    "ignore the noise outside and {}",
    "{}, then wait for the next command",
    "when you are ready, {}, thank you",
    "the weather is nice today, so {}",
)
"""Distractor templates of the semantic suite, never used in training."""


def expand(names: str | Sequence[str]) -> tuple[str, ...]:
    """Perturbation names from names and suite names (``vision`` = its five); a ValueError
    names the valid ones."""
    out: list[str] = []
    for name in split_names(names):
        if name in SUITES:
            out += [n for n in SUITES[name] if n not in out]
        elif name in FAMILY:
            out += [] if name in out else [name]
        else:
            valid = ", ".join([*OOD_SUITES, *FAMILY])
            raise ValueError(f"unknown perturbation {name!r}; choose suites or perturbations among: {valid}")
    return tuple(out)


def draw(rng: np.random.Generator, key: str, heldout: bool) -> float:
    """One value of scalar ``key`` from its training or held-out intervals (``RANGES``)."""
    intervals = RANGES[key][int(heldout)]
    lo, hi = intervals[int(rng.integers(len(intervals)))]
    if key in LOG_UNIFORM:
        return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))
    return float(rng.uniform(lo, hi))


def draw_color(rng: np.random.Generator, heldout: bool) -> tuple[float, float, float]:
    """An RGB colour whose hue lies in a training (even) or held-out (odd) hue bin."""
    bin_ = 2 * int(rng.integers(HUE_BINS // 2)) + int(heldout)
    hue = (bin_ + rng.uniform()) / HUE_BINS
    return colorsys.hsv_to_rgb(hue, rng.uniform(0.5, 0.9), rng.uniform(0.6, 1.0))


def hue_bin(rgb: Sequence[float]) -> int:
    """The hue bin of a colour drawn by :func:`draw_color` (tests check train/held-out disjointness)."""
    return int(colorsys.rgb_to_hsv(*rgb)[0] * HUE_BINS) % HUE_BINS


def random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def instruction_variants(canonical: str, paraphrases: dict[str, Sequence[str]], names: Sequence[str],
                         heldout: bool) -> tuple[list[str], dict[str, range]]:
    """A task's instruction variants under perturbations ``names``: the canonical instruction
    first (index 0), then one segment per semantic perturbation; returns the list and each
    segment's index range. ``paraphrases`` holds the task's ``train`` and ``heldout`` lists."""
    split = "heldout" if heldout else "train"
    variants, segments = [canonical], {}
    for name in names:
        if name == "paraphrase":
            if not paraphrases.get(split):
                raise ValueError(f"no {split} paraphrases of {canonical!r}: the semantic perturbations need them")
            segment = list(paraphrases[split])
        elif name == "distractor":
            segment = [t.format(canonical) for t in (HELDOUT_DISTRACTORS if heldout else TRAIN_DISTRACTORS)]
        else:
            continue
        segments[name] = range(len(variants), len(variants) + len(segment))
        variants += segment
    return variants, segments


@dataclass(frozen=True)
class Perturbations:
    """Which perturbations a simulator applies, and from which ranges (see the module doc)."""

    names: tuple[str, ...] = ()
    """Perturbation names (``expand`` resolves suite names)."""
    heldout: bool = False
    """False: training ranges, all ``names`` every episode; True: held-out ranges, one per episode."""

    def __post_init__(self) -> None:
        object.__setattr__(self, "names", expand(self.names))
        if self.heldout and not self.names:
            raise ValueError("held-out perturbations need at least one name")

    def __bool__(self) -> bool:
        return bool(self.names)

    @property
    def semantic(self) -> tuple[str, ...]:
        return tuple(n for n in self.names if FAMILY[n] == "semantic")

    def episode_rng(self, seed: int | None, stream: np.random.Generator) -> np.random.Generator:
        """The episode's own generator: from the reset seed, else one draw of the env's stream."""
        if seed is None:
            seed = int(stream.integers(2**62))
        return np.random.default_rng([int(seed), 0x9E37])

    def episode_names(self, seed: int | None, rng: np.random.Generator) -> tuple[str, ...]:
        """The perturbations of one episode: all of them in training; in a suite the one at
        ``seed % len(names)`` (unseeded: a random one)."""
        if not self.heldout:
            return self.names
        return (self.pick(seed) if seed is not None else self.names[int(rng.integers(len(self.names)))],)

    def pick(self, seed: int) -> str:
        """The perturbation a suite applies to the episode reset with ``seed``."""
        return self.names[int(seed) % len(self.names)]

    def sample(self, names: Sequence[str], rng: np.random.Generator) -> dict[str, dict]:
        """Parameters of perturbations ``names`` for one episode, simulator-independent:
        colours as RGB, scalars as in ``RANGES``, camera pose as a shift vector and a rotation
        (axis, degrees), semantic ones as ``u`` in [0, 1) (which variant of their segment)."""
        params: dict[str, dict] = {}
        held = self.heldout
        for name in names:
            if name.endswith("_color"):
                params[name] = {"rgb": draw_color(rng, held)}
            elif name == "camera_pose":
                params[name] = {"shift": draw(rng, "camera_shift", held) * random_unit(rng),
                                "axis": random_unit(rng), "degrees": draw(rng, "camera_tilt", held)}
            elif name == "object_position":
                if held:  # training positions are the task's own range: nothing to change
                    params[name] = {"margin": POSITION_MARGIN}
            elif name in ("paraphrase", "distractor"):
                params[name] = {"u": float(rng.uniform())}
            else:
                params[name] = {"factor" if name in LOG_UNIFORM else "std": draw(rng, name, held)}
        return params

    def instruction_index(self, segments: dict[str, range], count: int, params: dict[str, dict]) -> int:
        """The instruction variant of an episode: in a suite, one of the chosen perturbation's
        segment; in training, any of the ``count`` variants (canonical included)."""
        chosen = [n for n in params if n in segments]
        if not chosen:
            return 0
        u = params[chosen[0]]["u"]
        span = segments[chosen[0]] if self.heldout else range(count)
        return span[min(int(u * len(span)), len(span) - 1)]
