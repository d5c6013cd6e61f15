import pytest
import torch

from stepnft.policies.language import LanguageEncoder


def test_default_encoder_offline_and_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    enc = LanguageEncoder(cache_dir=tmp_path)
    emb = enc.embed(["pick up the puck", "open the door", "pick up the puck"])
    assert emb.shape == (3, 384)
    torch.testing.assert_close(emb[0], emb[2])
    sim = torch.nn.functional.cosine_similarity(emb[0], emb[1], dim=0)
    assert sim < 0.9
    # A second encoder reads the disk cache and never loads the model.
    again = LanguageEncoder(cache_dir=tmp_path)
    torch.testing.assert_close(again.embed(["open the door"])[0], emb[1])
    assert again._model is None


def test_loads_a_locally_created_checkpoint(tmp_path):
    """Real loading code for other encoders, on a tiny model built here (no download)."""
    from sentence_transformers import SentenceTransformer, models
    from transformers import BertConfig, BertModel, BertTokenizerFast

    from stepnft.policies.language import resolve_encoder_path

    base = resolve_encoder_path("default")
    tok = BertTokenizerFast.from_pretrained(base)
    bert_dir = tmp_path / "tiny-bert"
    BertModel(BertConfig(vocab_size=tok.vocab_size, hidden_size=32, num_hidden_layers=1, num_attention_heads=2,
                         intermediate_size=64)).save_pretrained(bert_dir)
    tok.save_pretrained(bert_dir)
    word = models.Transformer(str(bert_dir))
    st_dir = tmp_path / "tiny-st"
    SentenceTransformer(modules=[word, models.Pooling(32)]).save(str(st_dir))
    enc = LanguageEncoder(str(st_dir))
    assert enc.embed(["reach the goal"]).shape == (1, 32) and enc.dim == 32


def test_missing_encoder_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="cannot load language encoder"):
        LanguageEncoder(str(tmp_path / "missing")).embed(["x"])


def test_a_damaged_cache_entry_is_recomputed(tmp_path):
    enc = LanguageEncoder(cache_dir=tmp_path)
    first = enc.embed(["open the door"])
    (entry,) = list(tmp_path.glob("*.pt"))
    entry.write_bytes(entry.read_bytes()[:20])  # truncated, as by a kill mid-write before writes were atomic
    torch.testing.assert_close(LanguageEncoder(cache_dir=tmp_path).embed(["open the door"]), first)
    assert not list(tmp_path.glob(".*tmp"))
