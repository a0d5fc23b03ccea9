"""The mapping core: pure, synchronous, deterministic numpy/OpenCV code (no I/O)."""
