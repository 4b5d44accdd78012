"""Flying Arena: the shared library of the arena services and the user client."""
