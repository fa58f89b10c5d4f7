"""The command lines, each a module with ``main(argv) -> exit status``:

``design`` (the ``f2f-design`` command), ``cotrain`` (the whole run), ``evaluate`` (the paper's
tables), ``make_dataset`` and ``make_objects``.  ``experiments/*.py`` and ``python -m
f2f_jax.cli.<name>`` run them.
"""
