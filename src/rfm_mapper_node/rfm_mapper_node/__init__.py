"""rfm mapper node: pose averaging, object tracks, relocalization, map persistence (paper 3.5-3.6)."""
