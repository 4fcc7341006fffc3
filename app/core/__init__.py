"""scandiff's numeric core: formats, detectors, EMD, registration, localisation.

Usable from a notebook; imports only numpy, scipy, pykdtree, small_gicp and the format
libraries (scikit-learn and POT only in the tests, as the references the detectors reproduce),
never the web, database or settings layers (a test enforces this).
"""

from app.core.threads import prefer_passive_openmp_waits

prefer_passive_openmp_waits()
