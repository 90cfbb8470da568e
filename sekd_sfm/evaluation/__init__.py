"""Evaluation primitives that ``bench/`` and ``train/`` share, below both (it imports neither).

- ``metrics``: homography corner error, matching accuracy, repeatability, pose errors and AUC;
- ``datasets``: readers of HPatches-layout sequences and of scenes with ground-truth cameras;
- ``strecha``: the Strecha ``.camera`` format and relative-pose errors;
- ``samplers``: the random geometric and photometric changes of images (training pairs,
  distillation crops, the localisation and scale benchmarks' photos).

Nothing is imported here: ``bench/scale`` loads ``samplers`` in child processes whose memory is
measured, and the package must not pull torch into them.
"""
