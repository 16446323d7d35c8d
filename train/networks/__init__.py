"""Segments and the networks fitted to them.

- :mod:`.segments`       the k-d split into segments, CPCA-style merging, seam margins
- :mod:`.network`        the frequency-encoded transfer MLP (and residual networks)
- :mod:`.grid_encoding`  the multiresolution feature-grid networks
- :mod:`.fit`            fitting one network (loss, Adam, schedule, early stop)
- :mod:`.rightsize`      choosing a segment's network by the build's sizing rule
"""
