"""benchmarks/ablations.py: every row is a variant `stepnft compare` knows, and the verdicts
read the interval on the side the paper claims."""

import importlib.util
import math
import sys
from pathlib import Path

import pytest

from stepnft.algos.variants import VARIANTS

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ablations():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        spec = importlib.util.spec_from_file_location("ablations_benchmark", ROOT / "benchmarks" / "ablations.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[spec.name] = module  # its dataclasses look their module up
        spec.loader.exec_module(module)
        yield module
    finally:
        sys.modules.pop("ablations_benchmark", None)
        sys.path.remove(str(ROOT / "benchmarks"))


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
