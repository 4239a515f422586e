"""From segments to measured shape, in the order data flows: calibration (pixels to
millimetres), the turntable axis, assembly of views into sections, outlier rejection,
coverage and bridging, per-point precision, Elliptical Fourier Descriptors, the mesh and
its measurements; ``pipeline`` runs them in that order."""
