"""Device and log drivers: bytes in, typed samples (``mapping.samples``) out, and back."""
