"""3D Slicer scenes of EMReg's results, built with Slicer's own MRML (``slicer`` package).

Inside 3D Slicer ``slicer`` is the application's; outside it, the optional ``slicer-core``
wheel (``pip install 'emreg[slicer]'``) provides the same MRML nodes, storage nodes, module
logics and ``slicer.util`` array helpers, without Qt. This package uses nothing else, so the
3D Slicer module's Logic (``EMRegModule/slicer/EMReg.py``) and the scene bundle
``OUT/EMReg.mrb`` written by ``emreg run`` / ``emreg report`` show the same nodes.

Modules, one way (each only imports those before it): :mod:`.mrml` (Slicer's MRML: is it there, a scene with
the module logics Slicer registers), :mod:`.mrb` (the bundle's zip: Slicer's scene folder zipped by EMReg, the
CT's voxels copied from its file or compressed from memory), :mod:`.nodes` (one node per kind of result, on any
scene), :mod:`.run_scene` (what a run shows, from :class:`~EMRegModule.io.run_folder.RunFolder`, and the nodes of
it), :mod:`.bundle` (``OUT/EMReg.mrb`` of a run, in this process or a child process).

Frames: EMReg's image space is the CT's LPS space; Slicer's world is RAS. Points of image
space are flipped (x, y negated). ``ReferenceToImage`` becomes the linear transform node
``ReferenceToImage`` holding ``ReferenceToRAS = LPS_TO_RAS @ ReferenceToImage``; nodes in the
Reference frame (calibration points, the probe pose ``ProbeToReference``) are placed under it
with their coordinates unchanged, as PLUS and SlicerIGT do for tracker-side frames.
"""
