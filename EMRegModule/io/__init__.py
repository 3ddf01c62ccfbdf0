"""File I/O: CT volumes, tracking recordings, Slicer markups, ITK transforms, case folders.

Every writer is atomic (temporary file in the same folder, then rename).
"""
