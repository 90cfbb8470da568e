"""Benchmarks of a living map (``sekd bench maps ...``): localizing new photos, extending a model,
triangulating from known poses, georeferencing; each scored against known cameras."""
