"""Input/output: images, time synchronisation, message conversions (and later: bags)."""
