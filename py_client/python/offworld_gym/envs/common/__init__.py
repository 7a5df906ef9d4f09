"""Names shared by every OffWorld environment."""
