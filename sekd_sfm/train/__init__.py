"""Self-evolving training of SEKD (SPEC_TRAINING.md)."""
