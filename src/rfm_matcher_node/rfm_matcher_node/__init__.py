"""rfm matcher node: keyframes and a view graph of verified 4-DoF relative poses (paper 3.2-3.4)."""
