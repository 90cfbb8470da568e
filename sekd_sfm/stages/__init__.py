"""The stages, each one module, in the order data flows through them.

    keyframes   videos -> images/<video>/<frame>.jpg  (sharp frames, by motion or a count per video)
    extract     images -> features.h5                 (keypoints, descriptors; the global descriptors: retrieval)
    pairs       features.h5 -> pairs.txt              (exhaustive, sequential, retrieval, GPS neighbours)
    match       features.h5 + pairs.txt -> matches.h5
    refine      features + matches -> features-refined.h5
    database    -> database.db                        (COLMAP import and geometric verification)
    chance      database.db -> database.db            (verified pairs no better than chance dropped)
    viewgraph   database.db -> database.db            (verified pairs that disagree with the view graph dropped)
    mapping     database.db -> models                 (mapper_worker: the mapper's child process;
                                                        principal_point: the principal-point test;
                                                        hierarchical: clusters (partition) on the executor,
                                                        merged in the child (cluster_merge))
    modelcheck  models + database.db -> record         (verified pairs a model contradicts: folded models)
    georef      models -> models in a local ENU frame  (EXIF GPS)
    export      model -> text, PLY, HTML, nerfstudio   (export_nerfstudio)

``colmap`` holds the pycolmap helpers the stages share. A stage knows nothing of the pipelines
that call it (``sekd_sfm.pipelines``); work spread over items runs through ``sekd_sfm.execution``.
"""
