"""What is kept: the scan library (SQLite), the files a scan writes (PLY, ``report.json``),
the compact record and the DICOM object."""
