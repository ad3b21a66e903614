"""File infrastructure shared by every reader and writer: atomic files, checks that name the file, safe unpickling.

Nothing here knows a capture format: ``files`` (sha256, atomic replacement), ``reader_checks`` (the
``CaptureFormatError`` checks of values read from files), ``text_lines`` (line-numbered tokenising of
text files), ``safe_pickle`` (numpy data of pickles without running them) and ``hdf5_heaps`` (an HDF5
global-heap check before libhdf5 reads a file).
"""
