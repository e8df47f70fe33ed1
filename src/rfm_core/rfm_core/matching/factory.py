"""The object matcher by name (the learned one loads its weights on first use)."""
from __future__ import annotations

from rfm_core.matching.classical import ClassicalMatcher
from rfm_core.matching.config import MatchingConfig
from rfm_core.matching.learned import LearnedMatcher

__all__ = ['make_matcher']


def make_matcher(kind: str, config: MatchingConfig | None = None, weights=None, on_fallback=None):
    """'learned' (falls back to classical where it has no weights) or 'classical'."""
    config = config or MatchingConfig()
    if kind == 'classical':
        return ClassicalMatcher(config)
    if kind == 'learned':
        return LearnedMatcher(config, weights=weights or None, fallback=ClassicalMatcher(config), on_fallback=on_fallback)
    raise ValueError(f"unknown matcher {kind!r}; choose 'learned' or 'classical'")
