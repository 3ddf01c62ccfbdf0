"""Accuracy studies on simulated data (``emreg study NAME``), run on Dask; see :mod:`.runner`."""

from .catalog import STUDIES, Study, Summary
from .runner import format_table, run_study

__all__ = ["STUDIES", "Study", "Summary", "format_table", "run_study"]
