"""hydra/launcher options shared by the entry points (their configs' hydra.searchpath)."""
