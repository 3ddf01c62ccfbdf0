"""SimpleITK's voxel types by value and name, for the code that decides on them without a SimpleITK image.

``emreg detect`` reads an uncompressed DICOM series into numpy memory (:mod:`EMRegModule.io.dicom_read`): nothing in
it needs SimpleITK itself, whose 270 MB library takes some 50 ms of CPU to load, on the path before any slice is
decoded. Core's CT geometry check (:mod:`.ct`) and the readers share them.
The values are SimpleITK's ``PixelIDValueEnum`` (``sitk.sitkInt16`` is :data:`INT16`, the same int) and the names
``sitk.GetPixelIDValueAsString`` gives; the tests check both against SimpleITK.
"""

from __future__ import annotations

INT8, UINT8, INT16, UINT16, INT32, UINT32, INT64, UINT64, FLOAT32, FLOAT64 = range(10)

#: ``sitk.GetPixelIDValueAsString`` of each scalar type.
NAMES = {INT8: "8-bit signed integer", UINT8: "8-bit unsigned integer", INT16: "16-bit signed integer",
         UINT16: "16-bit unsigned integer", INT32: "32-bit signed integer", UINT32: "32-bit unsigned integer",
         INT64: "64-bit signed integer", UINT64: "64-bit unsigned integer", FLOAT32: "32-bit float",
         FLOAT64: "64-bit float"}

#: The scalar types (one component per voxel).
SCALAR = frozenset(NAMES)
FLOATS = frozenset({FLOAT32, FLOAT64})

#: The numpy voxel type (its name) of each type EMReg's own readers fill (the file layouts of
#: :mod:`EMRegModule.io.ct_header`, the DICOM slices numpy decodes), and each of those names' SimpleITK type.
NUMPY_NAMES = {INT8: "int8", UINT8: "uint8", INT16: "int16", UINT16: "uint16", INT32: "int32", UINT32: "uint32",
               FLOAT32: "float32", FLOAT64: "float64"}
BY_NUMPY_NAME = {name: value for value, name in NUMPY_NAMES.items()}
