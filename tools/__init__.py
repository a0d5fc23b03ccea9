"""Tools around the core: the survey simulator and friends."""
