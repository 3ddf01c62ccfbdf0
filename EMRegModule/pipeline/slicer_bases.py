"""3D Slicer's scripted-module bases outside the Slicer application, for ``EMRegModule/slicer/EMReg.py``.

The slicer-core wheel has Slicer's MRML, storage nodes, module logics and slicer.util, but not Slicer's Python
package for scripted modules (it needs Qt and the application). So that the Logic and the self-test run on
slicer-core's MRML (in CI), their bases are replaced by the parts of Slicer's bases they use; the module
description and the Widget need the application and refuse to start. Plain Python (3.9 too: old Slicers load
this file before they can say they are too old).
"""

import logging
import unittest


class ScriptedLoadableModuleLogic:
    """Outside Slicer: what Slicer's base does in its constructor (the module name, singleton parameter
    node); its parameter-node helpers are not provided (EMRegLogic does not use them)."""

    def __init__(self, parent=None):
        self.moduleName = type(self).__name__[: -len("Logic")]
        self.isSingletonParameterNode = True

class ScriptedLoadableModuleTest(unittest.TestCase):
    """Outside Slicer: a unittest.TestCase whose delayDisplay logs (no message box)."""

    def delayDisplay(self, message, requestedDelay=None, msec=None):
        logging.info("EMReg test: %s", message)

class _NeedsSlicerApplication:
    def __init__(self, *args, **kwargs):
        raise RuntimeError(f"{type(self).__name__} needs the 3D Slicer application (Qt); outside it use "
                           "EMRegLogic (MRML only) or the 'emreg' command")

class ScriptedLoadableModule(_NeedsSlicerApplication):
    pass

class ScriptedLoadableModuleWidget(_NeedsSlicerApplication):
    pass
