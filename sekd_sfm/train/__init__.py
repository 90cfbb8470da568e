"""Self-evolving training of SEKD (docs/method.md "Training")."""
