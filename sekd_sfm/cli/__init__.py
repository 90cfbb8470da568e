"""The ``sekd`` command line (installed as ``sekd_sfm.cli``)."""
