"""Readers and writers of file formats, one module each (the only I/O of :mod:`pwlreg.core`
besides :mod:`pwlreg.core.io`, which they are taking over)."""
