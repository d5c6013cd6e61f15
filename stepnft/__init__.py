"""stepnft: online RL fine-tuning of flow-matching robot policies with π-StepNFT."""

import os
import sys
import warnings

# Same numbers on every x86 CPU. PyTorch's CPU kernels sum in another order with AVX-512: on an
# AVX-512 machine, with every package version pinned, oneDNN's kernels moved the main command's
# SFT start (0.436 -> 0.434) and ATen's vectorised kernels (elementwise ops and reductions) its RL
# run (0.768 -> 0.722), docs/experiments.md §14. Capping both at AVX2 gives the AVX2 machines'
# figures bit for bit. oneDNN reads its cap when it first runs a kernel; ATen picks a kernel when
# an op first runs, so import stepnft before torch runs anything (the CLI does). A value you set
# is kept (e.g. ATEN_CPU_CAPABILITY=avx512 to use AVX-512 again;
# `default` would mean no vector kernels at all).
os.environ.setdefault("ONEDNN_MAX_CPU_ISA", "AVX2")
os.environ.setdefault("ATEN_CPU_CAPABILITY", "avx2")

if os.environ["ATEN_CPU_CAPABILITY"] == "avx2" and "torch" in sys.modules:
    # Torch imported first is fine; an op run first has fixed ATen's kernels for this process.
    if sys.modules["torch"].backends.cpu.get_cpu_capability() == "AVX512":
        warnings.warn("torch ran an op before stepnft was imported, so ATen keeps its AVX-512 kernels and runs may "
                      "not give the published figures: import stepnft before torch computes anything "
                      "(or export ATEN_CPU_CAPABILITY=avx512 to choose AVX-512 and silence this)", RuntimeWarning, stacklevel=2)

__version__ = "0.1.0"
