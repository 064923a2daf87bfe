"""D2A command line (``d2a``)."""
