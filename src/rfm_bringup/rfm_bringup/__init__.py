"""rfm bringup: the rfm command line (sim, play, record) and, later, launch files."""
