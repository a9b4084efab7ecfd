"""Losses registered by name (registry kind ``loss``)."""
