"""The ``wl`` command line and the report: the top floor (imports every package; nothing imports it)."""
