"""The visual scene built from the core scene (pyrender)."""
