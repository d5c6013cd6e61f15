"""LeRobot's flow VLAs (SmolVLA; π0 / π0.5 where they build) behind stepnft's policy interface.

Needs the optional LeRobot environment (``bash scripts/bootstrap.sh --lerobot`` makes
``.venv-lerobot``; docs/lerobot.md). Importing this package imports nothing from LeRobot; the
modules that do (``smolvla``, ``pi0``, ``processor``, ``tiny``) call :func:`require_lerobot`
first, so a missing LeRobot is one line saying what to do.

- ``configuration``: the stepnft-side settings of a LeRobot policy folder (no LeRobot import).
- ``processor``: raw stepnft observations -> LeRobot's own pre-processor; actions back through
  its post-processor (un-normalised the way LeRobot does).
- ``adapter``: what every LeRobot flow VLA shares (load / save through LeRobot's own
  ``from_pretrained`` / ``save_pretrained``, trainable parts, action spaces).
- ``smolvla``, ``pi0``: the prefix (encoded once per policy call, its KV cache) and the
  action expert's denoising step of each model.
- ``tiny``: offline VLM configurations (tiny, or SmolVLA's real size without weights) and new
  SmolVLA policy folders built from them.
"""

from __future__ import annotations

LEROBOT_HINT = ("it needs LeRobot: create the LeRobot environment with `bash scripts/bootstrap.sh --lerobot` "
                "and run stepnft with `.venv-lerobot/bin/python -m stepnft.cli ...` (docs/lerobot.md)")


def require_lerobot() -> None:
    """Raise ImportError with one line saying how to get LeRobot when it is not installed."""
    try:
        import lerobot  # noqa: F401
    except ImportError as err:
        raise ImportError(f"LeRobot is not installed in this environment: {LEROBOT_HINT}") from err
