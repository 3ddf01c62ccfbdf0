"""The pipeline: the stage table (:mod:`EMRegModule.stages`), the results held and what a new one makes stale
(:mod:`.results`), the provenance of every output written (:mod:`.recorder`). The controller
(:mod:`EMRegModule.pipeline.controller`) sequences them; nothing here imports the faces (command line, Slicer)."""
