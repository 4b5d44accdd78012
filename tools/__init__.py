"""Developer tools (the wire-doc generator, the layer check): not part of the installed runtime."""
