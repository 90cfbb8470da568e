"""sekd_sfm: SEKD learned local features for COLMAP reconstruction.

Data flows images -> features.h5 -> pairs -> matches.h5 -> database -> model -> report;
each stage is one function taking paths and a configuration and returning the path
it wrote (``extract.extract_features``, ...), and the ``sekd`` CLI only parses options.
"""
__version__ = "0.2.0"
