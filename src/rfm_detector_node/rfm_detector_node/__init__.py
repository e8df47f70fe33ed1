"""rfm detector node: per-frame metric 3D boxes and embeddings (paper section 3.1)."""
