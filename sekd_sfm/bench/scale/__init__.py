"""``sekd bench scale``: how every stage grows with the number of photos, on generated scenes with known cameras.

* ``scene``: a city block of box-shaped buildings textured with photos, rendered by exact
  homographies from cameras walking around it; ground-truth cameras and co-visibility.
* ``measure``: wall time, peak RSS and bytes written of a function run in its own process.
* ``run``: our pipeline and pycolmap's SIFT pipeline at several sizes, growth exponents, report.

Nothing is imported here: the measured child processes (``python -m ...measure``) must hold
only what the measured function needs.
"""
