"""A reference scan's work kept between its comparisons: the geometry cache.

A site's reference is compared with every new scan of the site; what a comparison works out from
the reference alone is kept in one file beside it and read back by the next comparisons.

* :mod:`~app.core.cache.geometry`: the file (:class:`~app.core.cache.geometry.GeometryCache`),
  its key and the reference's k-nearest-neighbour geometry;
* :mod:`~app.core.cache.geometry_format`: the file's byte layout and checksums;
* :mod:`~app.core.cache.reference_memory`: the reference's alignment arrays handed between
  alignments (:class:`~app.core.cache.reference_memory.ReferenceMemory`);
* :mod:`~app.core.cache.reference_alignment`: those arrays kept in the file;
* :mod:`~app.core.cache.reference_origin`: the reference's resolved sensor origin kept in the
  file.
"""
