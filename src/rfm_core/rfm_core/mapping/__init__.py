"""Mapping (paper 3.5-3.6 and appendix): pose averaging, object tracks, box refinement,
relocalization and map persistence."""
