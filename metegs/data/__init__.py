"""Data: scene descriptions from parsers, image loading and the training dataset."""
