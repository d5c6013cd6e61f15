"""``python -m stepnft.policies.lerobot new --out DIR [--model smolvla|pi0|pi05] [...]``: a new
SmolVLA, π0 or π0.5 policy folder built on an offline configuration (``stepnft.policies.lerobot.tiny``); ``vlm --out DIR --size tiny``
writes only the VLM configuration (for ``SmolVLAConfig(vlm_model_name=DIR, load_vlm_weights=False)``);
``merge --policy DIR --out DIR2`` folds a policy's LoRA adapters into its weights (a plain
LeRobot folder in ``DIR2/lerobot``)."""

from __future__ import annotations

import sys


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    usage = "usage: python -m stepnft.policies.lerobot {new,vlm,merge} --out DIR [...]  (--help after the command)"
    if not argv or argv[0] not in ("new", "vlm", "merge"):
        print(usage, file=sys.stderr if argv and argv[0] not in ("-h", "--help") else sys.stdout)
        return 0 if argv and argv[0] in ("-h", "--help") else 2
    import tyro

    from stepnft.policies.lerobot.tiny import NewVLA, new_vla, write_vlm

    try:
        if argv[0] == "vlm":
            from dataclasses import dataclass
            from typing import Literal

            @dataclass
            class Vlm:
                """Write an offline SmolVLM configuration folder."""
                out: str
                """Folder to write."""
                size: Literal["tiny", "smolvla"] = "tiny"
                """tiny, or smolvla (SmolVLA's real backbone architecture, no weights)."""

            args = tyro.cli(Vlm, args=argv[1:], prog="python -m stepnft.policies.lerobot vlm")
            print(f"wrote {write_vlm(args.out, args.size)}")
        elif argv[0] == "merge":
            from dataclasses import dataclass
            from pathlib import Path

            from stepnft.policies.base import load_policy

            @dataclass
            class Merge:
                """Fold a policy's LoRA adapters into its weights and save it as a plain policy."""
                policy: str
                """Policy folder with LoRA adapters (config.json lora_rank > 0, lora.safetensors)."""
                out: str
                """New folder for the merged policy (its lerobot/ is LeRobot's fine-tuned model)."""

            args = tyro.cli(Merge, args=argv[1:], prog="python -m stepnft.policies.lerobot merge")
            out = Path(args.out)
            if out.exists() and any(out.iterdir()):
                raise ValueError(f"{out} is not empty: choose a new folder for the merged policy")
            policy = load_policy(args.policy)
            if not getattr(policy.config, "lora_rank", 0):
                raise ValueError(f"{args.policy} has no LoRA adapters (lora_rank 0): nothing to merge")
            policy.merge_lora().save_pretrained(out)
            print(f"wrote {out} (adapters merged)")
        else:
            spec = tyro.cli(NewVLA, args=argv[1:], prog="python -m stepnft.policies.lerobot new")
            policy = new_vla(spec)
            total = sum(p.numel() for p in policy.parameters())
            trained = sum(p.numel() for p in policy.parameters() if p.requires_grad)
            label = {"smolvla": "SmolVLA", "pi0": "π0", "pi05": "π0.5"}[spec.model]
            print(f"wrote a new {label} ({total / 1e6:.2f} M parameters, {trained / 1e6:.2f} M trained) to {spec.out}")
    except (ValueError, FileNotFoundError) as err:
        print(f"error: {str(err).splitlines()[0]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
