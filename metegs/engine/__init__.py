"""Training engine: optimisers, the trainer loop and checkpoints."""
