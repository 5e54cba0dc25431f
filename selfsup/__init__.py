"""Self-supervised point-light estimation built on :mod:`render`."""
