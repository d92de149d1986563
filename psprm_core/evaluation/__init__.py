"""Evaluation and tooling around the planning library: the benchmark harness (``psprm bench``), the ``psprm perf``
measurements, reference routes, backend overheads and projections, ``psprm simulate``, plots, the device check and
the pybullet reference checks. These modules import the library; the library never imports them."""
