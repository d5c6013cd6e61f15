"""The paper's out-of-distribution claims: each verdict from a paired interval, and the report's
table of them for every PPO row."""

import math

import pytest

from stepnft.compare.claims import CLAIMS, PAPER_PI0, Claim, verdict
from stepnft.compare.report import claims_markdown, task_differences_markdown
from stepnft.compare.stats import mean_ci

LEVEL = Claim("ind", "level", "level", 0.05)
AHEAD = Claim("ood_average", "ahead", "ahead")
VISION = Claim("vision", "ahead by 8", "ahead", 0.08)
NAN = math.nan


@pytest.mark.parametrize("claim, diff, expected", [
    (LEVEL, (0.01, -0.03, 0.05), "reproduced: level within ±5 points"),
    (LEVEL, (0.01, -0.20, 0.22), "inside the noise"),  # holds 0, but also a 20-point gap
    (LEVEL, (0.06, 0.02, 0.10), "not reproduced: π-StepNFT ahead"),
    (LEVEL, (-0.06, -0.10, -0.02), "not reproduced: PPO ahead"),
    (AHEAD, (0.11, 0.04, 0.18), "reproduced"),
    (AHEAD, (0.02, -0.03, 0.07), "inside the noise"),
    (AHEAD, (-0.07, -0.12, -0.02), "not reproduced: PPO ahead"),
    (VISION, (0.12, 0.09, 0.15), "reproduced"),
    (VISION, (0.05, 0.01, 0.09), "inside the noise"),  # ahead, but a lead of 8 is not excluded
    (VISION, (0.06, 0.02, 0.07), "not reproduced: the interval excludes a 8-point lead"),
    (VISION, (-0.05, -0.09, -0.01), "not reproduced: PPO ahead"),
    (AHEAD, (0.30, NAN, NAN), "undecided: one paired seed gives no interval"),
    (AHEAD, (NAN, NAN, NAN), "no paired seeds"),
])
def test_verdict_reads_the_paired_interval(claim, diff, expected):
    assert verdict(claim, diff) == expected


def test_the_claims_are_the_papers_pi0_margins():
    paper = {c.suite: PAPER_PI0["π-StepNFT"][c.suite] - PAPER_PI0["PPO (Flow-SDE, critic)"][c.suite] for c in CLAIMS}
    assert paper["ood_average"] == pytest.approx(0.111) and paper["vision"] == pytest.approx(0.08)
    for claim in CLAIMS:  # the paper's own leads pass its "ahead" claims, measured tightly
        if claim.kind == "ahead":
            assert verdict(claim, (paper[claim.suite], paper[claim.suite] - 0.01, paper[claim.suite] + 0.01)) == \
                "reproduced", claim


def _row(per_seed):
    return {"per_seed": {s: {"ind": v[0], "vision": v[1], "semantic": None, "execution": v[2],
                             "ood_average": (v[1] + v[2]) / 2} for s, v in per_seed.items()}}


def test_the_report_tests_every_claim_on_every_ppo_row_paired_by_seed():
    rows = {"stepnft": _row({0: (0.8, 0.7, 0.3), 1: (0.7, 0.6, 0.3), 2: (0.9, 0.8, 0.4)}),
            "ppo": _row({0: (0.8, 0.5, 0.3), 1: (0.7, 0.4, 0.3), 2: (0.9, 0.6, 0.4)}),
            "ppo-shared": _row({0: (0.8, 0.7, 0.3), 1: (0.7, 0.6, 0.3)}),  # seed 2 did not finish
            "grpo": _row({0: (0.1, 0.1, 0.1)})}
    text = "\n".join(claims_markdown(rows, ["stepnft", "ppo", "ppo-shared", "grpo"], "stepnft"))
    assert "| π-StepNFT | 0.79 | 0.69 | 0.49 | 0.33 | 0.50 |" in text  # the paper's table beside ours
    lines = [line for line in text.splitlines() if "stepnft − " in line]
    assert len(lines) == 2 * 4 and not any("semantic" in line for line in lines)  # a suite not run: no claim
    vision = [line for line in lines if "vision" in line]
    # +0.20 on every seed: the interval is a point, above the 8-point margin.
    assert "| stepnft − ppo | 3 | +0.20 [+0.20, +0.20] | reproduced |" in vision[0]
    assert "| stepnft − ppo-shared | 2 | +0.00 [+0.00, +0.00] | not reproduced: the interval excludes" in vision[1]
    ood = [line for line in lines if "out of distribution" in line][0]
    assert format(mean_ci([0.1, 0.1, 0.1])[0], "+.2f") in ood and ood.endswith("| reproduced |")
    ind = [line for line in lines if "in distribution" in line][0]
    assert "reproduced: level within ±5 points" in ind  # the same ind on every seed
    assert claims_markdown(rows, ["stepnft", "grpo"], "stepnft") == []  # no PPO row: no claims


def test_the_suites_report_pairs_every_row_with_the_reference_per_suite_and_task():
    def tasks(vision, execution):
        return {"vision": dict(zip(["door", "faucet"], vision)), "execution": dict(zip(["door", "faucet"], execution))}

    rows = {"sft": {"per_task": {0: tasks((0.5, 0.5), (0.2, 0.4)), 1: tasks((0.4, 0.6), (0.2, 0.4))}},
            "stepnft": {"per_task": {0: tasks((0.8, 0.6), (0.4, 0.4)), 1: tasks((0.6, 0.8), (0.4, 0.6))}},
            "ppo": {"per_task": {0: tasks((0.6, 0.6), (0.4, 0.4)), 2: tasks((0.0, 0.0), (0.0, 0.0))}}}
    lines = task_differences_markdown(rows, "stepnft")
    table = [line for line in lines if line.startswith("| ") and "paired seeds" not in line]
    assert len(table) == 4 and not any(line.startswith("| stepnft ") for line in table)  # no reference row
    assert "| algorithm | suite | paired seeds | door | faucet | average |" in lines
    sft_vision = next(line for line in table if line.startswith("| SFT (start) | vision | 2 |"))
    # Per task over seeds (-0.3 and -0.2 on door), on average over every (seed, task) pair.
    assert sft_vision.split(" | ")[3].startswith(format(mean_ci([-0.3, -0.2])[0], "+.2f"))
    assert sft_vision.split(" | ")[5].startswith(format(mean_ci([-0.3, -0.2, -0.1, -0.2])[0], "+.2f"))
    # ppo pairs on seed 0 alone (its seed 2 has no stepnft run): one seed, no interval.
    assert "| ppo | vision | 1 | -0.20 " in "\n".join(table)
    assert task_differences_markdown({"stepnft": rows["stepnft"]}, "stepnft") == []
