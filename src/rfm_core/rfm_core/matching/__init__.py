"""Matching (paper sections 3.2-3.4): objects between two frames, their corners, and the
verified 4-DoF relative pose."""
