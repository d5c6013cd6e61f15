"""benchmarks/ablations.py: every row is a variant `stepnft compare` knows, and the verdicts
read the interval on the side the paper claims."""

import math

import pytest

from benchmark_loader import benchmark_module

from stepnft.algos.variants import VARIANTS


@pytest.fixture(scope="module")
def ablations():
    with benchmark_module("ablations") as module:
        yield module


def test_every_ablation_is_a_known_variant_of_stepnft(ablations):
    names = [a.variant for a in ablations.ABLATIONS]
    assert len(set(names)) == len(names)
    for name in [ablations.REFERENCE, *names]:
        assert VARIANTS[name].algo == "stepnft", name
    argv = ablations.compare_argv(ablations.parse_args(["--seeds", "0", "1"]), [0])
    assert argv[argv.index("--algos") + 1:argv.index("--seeds")] == [ablations.REFERENCE, *names]


@pytest.mark.parametrize(("sign", "diff", "expected"), [
    (-1, (-0.10, -0.15, -0.05), "reproduced"),
    (-1, (+0.10, +0.05, +0.15), "contradicted"),
    (-1, (-0.02, -0.08, +0.04), "not separated"),
    (+1, (+0.10, +0.05, +0.15), "reproduced"),
    (+1, (-0.10, -0.15, -0.05), "contradicted"),
    (+1, (0.0, math.nan, math.nan), "–"),
])
def test_verdicts(ablations, sign, diff, expected):
    assert ablations.verdict(sign, diff) == expected
