"""EMReg: automatic patient-to-image registration for electromagnetic surgical navigation.

The package is a GUI-free core (transforms, I/O, CT marker detection, tracking, pairing,
calibration, registration, navigation, evaluation, rendering) driven by a controller
(:mod:`EMRegModule.pipeline.controller`) and thin faces: the ``emreg`` command, the 3D Slicer
scripted module and an OpenIGTLink server.

Conventions: millimetres and degrees; image space is the CT's LPS physical space as
SimpleITK reports it; a transform named ``AToB`` maps points given in frame A into frame B.
"""

__version__ = "0.1.0"
