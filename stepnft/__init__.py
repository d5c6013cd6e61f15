"""stepnft: online RL fine-tuning of flow-matching robot policies with π-StepNFT."""

import os

# Same numbers on every x86 CPU. PyTorch's CPU kernels sum in another order with AVX-512: on an
# AVX-512 machine, with every package version pinned, oneDNN's kernels moved the main command's
# SFT start (0.436 -> 0.434) and ATen's vectorised kernels (elementwise ops and reductions) its RL
# run (0.768 -> 0.722), docs/experiments.md §14. Capping both at AVX2 gives the AVX2 machines'
# figures bit for bit. oneDNN reads its cap when it first runs a kernel; ATen picks a kernel when
# an op first runs, so import stepnft before torch runs anything (the CLI does). A value you set
# is kept (e.g. ATEN_CPU_CAPABILITY=default to use AVX-512 again).
os.environ.setdefault("ONEDNN_MAX_CPU_ISA", "AVX2")
os.environ.setdefault("ATEN_CPU_CAPABILITY", "avx2")

__version__ = "0.1.0"
