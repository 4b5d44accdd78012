"""One module per arena process: its wiring and a ``main``."""
