"""Densification strategies (registry kind ``densifier``); they see scene Gaussians only."""
