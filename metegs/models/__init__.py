"""Learned networks that a method adds to the scene Gaussians (the GTN of the weather branch)."""
