"""stepnft: online RL fine-tuning of flow-matching robot policies with π-StepNFT."""

import os

# Same numbers on every x86 CPU: PyTorch's oneDNN kernels take other code paths with AVX-512
# (summation order), which moved the main command's SFT start from 0.436 to 0.434 on an AVX-512
# machine with every package version pinned (docs/experiments.md §14). oneDNN reads this when it
# first runs a kernel, so it holds even if torch was imported first; a value you set is kept.
os.environ.setdefault("ONEDNN_MAX_CPU_ISA", "AVX2")

__version__ = "0.1.0"
