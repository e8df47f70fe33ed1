"""The object matcher by name, importing torch only for the learned one (nodes started with
``matcher:=classical`` never load it)."""
from __future__ import annotations

from rfm_core.matching.classical import ClassicalMatcher
from rfm_core.matching.config import MatchingConfig

__all__ = ['make_matcher']


def make_matcher(kind: str, config: MatchingConfig | None = None, weights=None, on_fallback=None):
    """'learned' (falls back to classical where it has no weights) or 'classical'."""
    config = config or MatchingConfig()
    if kind == 'classical':
        return ClassicalMatcher(config)
    if kind == 'learned':
        from rfm_core.matching.learned import LearnedMatcher  # noqa: PLC0415 - torch
        return LearnedMatcher(config, weights=weights or None, threads=1,
                              fallback=ClassicalMatcher(config), on_fallback=on_fallback)
    raise ValueError(f"unknown matcher {kind!r}; choose 'learned' or 'classical'")
