"""stepnft: online RL fine-tuning of flow-matching robot policies with π-StepNFT."""

__version__ = "0.1.0"
