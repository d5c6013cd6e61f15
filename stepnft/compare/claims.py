"""The paper's out-of-distribution claims and their verdicts on a comparison's suite results.

The π-StepNFT paper reports, for π0 on ManiSkill, that π-StepNFT and PPO (Flow-SDE, with a
critic) are level in distribution but π-StepNFT is ahead out of distribution, most under
vision and semantic shifts (:data:`PAPER_PI0`). :data:`CLAIMS` states each of those as a test
on the paired difference π-StepNFT − PPO (same seed, same SFT start) and :func:`verdict` reads
its 95 % interval: *reproduced*, *not reproduced* or *inside the noise*. A well-measured
"not reproduced" is a result; one paired seed gives no interval and no verdict.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

PAPER_PI0: dict[str, dict[str, float]] = {
    "SFT": {"ind": 0.384, "vision": 0.326, "semantic": 0.084, "execution": 0.132, "ood_average": 0.181},
    "PPO (Flow-SDE, critic)": {"ind": 0.788, "vision": 0.611, "semantic": 0.254, "execution": 0.315,
                               "ood_average": 0.393},
    "π-StepNFT": {"ind": 0.792, "vision": 0.691, "semantic": 0.491, "execution": 0.331, "ood_average": 0.504},
}
"""Success per suite, π0 on ManiSkill, as the paper reports it (its OOD table)."""


@dataclass(frozen=True)
class Claim:
    suite: str
    """The suite column the claim is about (``ood_average``: the mean of the OOD suites)."""
    text: str
    """The claim, as one line of the report."""
    kind: Literal["level", "ahead"]
    """``level``: the two are within ``margin`` of each other; ``ahead``: π-StepNFT leads by at
    least ``margin``."""
    margin: float = 0.0
    """``ahead``: the lead claimed (success, 0.08 = 8 points); ``level``: the band a difference
    must lie in to count as level (an equivalence test: an interval that holds 0 but is wider
    than the band cannot tell)."""


CLAIMS: tuple[Claim, ...] = (
    Claim("ind", "level with PPO in distribution, within ±5 points (paper: +0.4)", "level", 0.05),
    Claim("vision", "ahead of PPO under vision shifts by ≥ 8 points (paper: +8.0)", "ahead", 0.08),
    Claim("semantic", "ahead of PPO under semantic shifts (paper: +23.7)", "ahead"),
    Claim("execution", "level with PPO under execution shifts, within ±5 points (paper: +1.6)", "level", 0.05),
    Claim("ood_average", "ahead of PPO out of distribution on average (paper: +11.1)", "ahead"),
)
"""The paper's π0 ManiSkill findings as tests on π-StepNFT − PPO."""


def verdict(claim: Claim, diff: tuple[float, float, float]) -> str:
    """The claim against a paired difference ``(mean, lo, hi)`` (π-StepNFT − PPO, 95 % interval)."""
    mean, lo, hi = diff
    if math.isnan(mean):
        return "no paired seeds"
    if math.isnan(lo):
        return "undecided: one paired seed gives no interval"
    if claim.kind == "level":
        if lo > 0.0 or hi < 0.0:
            return f"not reproduced: {'π-StepNFT' if lo > 0 else 'PPO'} ahead"
        if -claim.margin <= lo and hi <= claim.margin:
            return f"reproduced: level within ±{claim.margin * 100:.0f} points"
        return "inside the noise"
    if lo > 0.0 and mean >= claim.margin - 1e-9:  # the paper's own 8.0-point lead passes
        return "reproduced"
    if hi < claim.margin:
        return "not reproduced: " + ("PPO ahead" if hi < 0 else f"the interval excludes a {claim.margin * 100:.0f}-point lead")
    return "inside the noise"
