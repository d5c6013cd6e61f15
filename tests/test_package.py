"""The package itself: what importing it sets up."""

import os
import subprocess
import sys


def _run(code: str, **env: str) -> str:
    base = {k: v for k, v in os.environ.items() if k not in ("ONEDNN_MAX_CPU_ISA", "ATEN_CPU_CAPABILITY")}
    return subprocess.run([sys.executable, "-c", code], env=base | env, capture_output=True, text=True,
                          check=True).stdout.strip()


def test_importing_stepnft_caps_onednn_and_aten_at_avx2_unless_set():
    """The same numbers on every x86 CPU (stepnft/__init__.py): oneDNN's and ATen's AVX-512
    kernels sum in another order. A value the user set is kept."""
    code = "import os, stepnft; print(os.environ['ONEDNN_MAX_CPU_ISA'], os.environ['ATEN_CPU_CAPABILITY'])"
    assert _run(code) == "AVX2 avx2"
    assert _run(code, ONEDNN_MAX_CPU_ISA="AVX512_CORE", ATEN_CPU_CAPABILITY="default") == "AVX512_CORE default"


def test_torch_dispatches_no_avx512_kernels_after_importing_stepnft():
    """Torch sees the cap under the name it reads: after importing stepnft, an AVX-512 CPU reports
    AVX2 (others report what they have, never more). It checks the variable reaches ATen, not which
    kernel each op took (bit-identical runs are checked by the main command, docs/experiments.md §14)."""
    code = ("import stepnft, torch; torch.randn(64).exp().sum(); "
            "print(torch.backends.cpu.get_cpu_capability())")
    assert _run(code) != "AVX512"


def _has_avx512() -> bool:
    return _run("import torch; print(torch.backends.cpu.get_cpu_capability())") == "AVX512"  # torch alone: no cap


def test_importing_stepnft_after_a_torch_op_warns_on_an_avx512_cpu():
    """ATen fixes its kernels when an op first runs: a script that computes before importing
    stepnft keeps AVX-512 and is told so; importing torch first (no op yet) is fine, and a value
    the user set is not second-guessed."""
    import pytest

    if not _has_avx512():
        pytest.skip("this CPU has no AVX-512: ATen never picks it, so there is nothing to warn about")
    warn = "import warnings, torch; warnings.simplefilter('error'); {op}import stepnft; print('ok')"
    late = subprocess.run([sys.executable, "-c", warn.format(op="torch.ones(3) + 1; ")], capture_output=True, text=True,
                          env={k: v for k, v in os.environ.items() if k != "ATEN_CPU_CAPABILITY"})
    assert late.returncode != 0 and "import stepnft before torch computes anything" in late.stderr
    assert _run(warn.format(op="")) == "ok"
    assert _run(warn.format(op="torch.ones(3) + 1; "), ATEN_CPU_CAPABILITY="avx512") == "ok"
