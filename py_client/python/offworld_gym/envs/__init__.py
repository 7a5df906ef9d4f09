"""OffWorld environments."""
