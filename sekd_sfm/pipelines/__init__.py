"""The pipelines: ordered lists of stages run over one :class:`~sekd_sfm.pipelines.run.Run`.

    run          the Run: validated settings, the one executor, the output folder, timings, progress
    record       the names of everything a run writes, and its record read back typed
    reconstruct  images -> COLMAP model (``sekd reconstruct``)
    extend       photos added to a model (``sekd reconstruct --extend``); extend_commit: its crash-safe commit
    localize     query photos -> poses against a model (``sekd localize``)
    triangulate  known poses -> 3D points (``sekd triangulate``)
    relpose      two photos -> relative pose (``sekd relpose``)
    report       match statistics, failure explanations, the console summary
"""
