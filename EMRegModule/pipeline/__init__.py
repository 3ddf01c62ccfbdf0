"""The pipeline: the stage table the controller walks (:mod:`.stages`: each stage of :mod:`EMRegModule.stages` with
its run, read and write, :mod:`.steps`), the inputs and results as immutable values (:mod:`.inputs`,
:mod:`.results`), the provenance of every output written (:mod:`.recorder`) and the report and bundle
(:mod:`.exporters`). The controller (:mod:`.controller`) only sequences them; nothing here imports the faces
(command line, Slicer)."""
