"""The package itself: what importing it sets up."""

import os


def test_importing_stepnft_caps_onednn_at_avx2_unless_set():
    """The same numbers on every x86 CPU (stepnft/__init__.py): oneDNN's AVX-512 kernels sum in
    another order. A value the user set is kept."""
    import subprocess
    import sys

    code = "import os, stepnft; print(os.environ['ONEDNN_MAX_CPU_ISA'])"
    env = {k: v for k, v in os.environ.items() if k != "ONEDNN_MAX_CPU_ISA"}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "AVX2"
    out = subprocess.run([sys.executable, "-c", code], env=env | {"ONEDNN_MAX_CPU_ISA": "AVX512_CORE"},
                         capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "AVX512_CORE"
