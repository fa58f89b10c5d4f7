"""What the benchmarks measure with: simulator agreement on mixed triples (``agreement``) and the
PyBullet peer of the original Fit2Form protocol (``pybullet_peer``, ``pybullet_runs``; the
``pybullet`` extra).  ``benchmarks/*.py`` parse flags and print; the logic they share lives here."""
